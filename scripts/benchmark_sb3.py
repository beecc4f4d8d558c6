"""Benchmark the Algorithm-1 agent against Stable-Baselines3 SAC, TD3 and PPO (issue 7;
agents.experiments.benchmark_sb3: the protocol, budgets and outputs are in its docstring).

    python scripts/benchmark_sb3.py --json docs/benchmark.json                # full benchmark
    python scripts/benchmark_sb3.py --json /tmp/q.json --quick --docs /tmp/q.md  # CI smoke test
    python scripts/benchmark_sb3.py --json b.json --backend ray               # on a Ray cluster
"""


from agents.experiments.benchmark_sb3 import QUICK, Args, run
from mbtsr.cli import main

if __name__ == "__main__":
    main(Args, run, outputs=("json", "docs"), folders=("out_dir",), presets={"--quick": QUICK})

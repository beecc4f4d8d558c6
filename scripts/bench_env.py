"""Benchmark the two-link arm env: env vs raw MuJoCo steps/s, Jacobian costs.

    python scripts/bench_env.py --json runs/bench_env.json
"""


from agents.cli import main
from agents.experiments.bench_env import Args, run

if __name__ == "__main__":
    main(Args, run, outputs=("json",))

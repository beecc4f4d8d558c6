"""Ablation of the Algorithm-1 agent: episodes to "solve" the arm per regularization and seed
(agents.experiments.agent_ablation).

    python scripts/agent_ablation.py                       # 3 regularizations x 5 seeds
    python scripts/agent_ablation.py --episodes 15 --workers 2 --json ablation.json
"""


from agents.experiments.agent_ablation import Args, run
from mbtsr.cli import main

if __name__ == "__main__":
    main(Args, run, outputs=("json",), folders=("out", "oracle_cache_dir"))

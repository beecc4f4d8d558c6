"""Planning at the control rate: ms per MPC step of the default planner per suite task (issue 45).

    python scripts/bench_planning.py --json docs/results/bench_ilqr/planning_rate.json \
        --figure docs/figures/planning_rate.png            # --help: the options
"""

from agents.experiments.bench_planning import Args, run
from mbtsr.cli import main

if __name__ == "__main__":
    main(Args, run, outputs=("json", "figure"))

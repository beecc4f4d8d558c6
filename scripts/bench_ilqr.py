"""Benchmark iLQR and MPC on the two-link arm against IPOPT and crocoddyl (issue 13).

    python scripts/bench_ilqr.py --json runs/bench_ilqr.json   # --help: the options
"""


from agents.cli import main
from agents.experiments.bench_ilqr import Args, run

if __name__ == "__main__":
    main(Args, run, outputs=("json",))

"""Benchmark of LTV identification (issue 3): fit time vs a generic solver, scaling in T.

    python scripts/bench_ltv.py --json runs/bench_ltv.json
"""


from agents.cli import main
from agents.experiments.bench_ltv import (  # first: sets the BLAS threads before numpy loads
    Args,
    run,
)

if __name__ == "__main__":
    main(Args, run, outputs=("json",))

"""Benchmark of the neural dynamics ensembles and their training (agents.experiments.bench_models).

    python scripts/bench_models.py --json runs/bench_models.json
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # BLAS reads it when numpy loads; --threads sets torch's


from agents.cli import main  # noqa: E402
from agents.experiments.bench_models import Args, run  # noqa: E402

if __name__ == "__main__":
    main(Args, run, outputs=("json",))

"""Model sizing and training measurements on suite tasks (agents.experiments.bench_model_sizes).

    python scripts/bench_model_sizes.py --task reacher --json runs/sizes_reacher.json
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # BLAS reads it when numpy loads; --threads sets torch's


from agents.cli import main  # noqa: E402
from agents.experiments.bench_model_sizes import Args, run  # noqa: E402

if __name__ == "__main__":
    main(Args, run, outputs=("json",))

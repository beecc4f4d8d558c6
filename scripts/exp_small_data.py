"""Wide ensembles on the first 1, 2 and 5 episodes of each suite task: held-out and Jacobian
error, none vs sampled vs exact (agents.experiments.exp_small_data).

    OMP_NUM_THREADS=1 python scripts/exp_small_data.py
    python scripts/exp_small_data.py --smoke
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # BLAS reads it when numpy loads; --threads sets torch's


from agents.cli import main  # noqa: E402
from agents.experiments.exp_small_data import SMOKE, Args, run  # noqa: E402

if __name__ == "__main__":
    main(Args, run, outputs=("json", "plot"), presets={"--smoke": SMOKE})

"""Held-out planning error of ensemble sizes on an agent run's own trajectories
(agents.experiments.diag_closed_loop_models).

    python scripts/diag_closed_loop_models.py --task pusher \
        --checkpoints runs/ckpt/pusher_cem-ilqr_none_seed0 --json runs/diag.json
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # BLAS reads it when numpy loads

from agents.cli import main  # noqa: E402
from agents.experiments.diag_closed_loop_models import Args, run  # noqa: E402

if __name__ == "__main__":
    main(Args, run, outputs=("json",))

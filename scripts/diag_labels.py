"""Jacobian errors of the LTV labels and of the model along an agent run
(agents.experiments.diag_labels).

    python scripts/diag_labels.py --task reacher --regularizations none exact --json runs/l.json
"""

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # BLAS reads it when numpy loads

from agents.cli import main  # noqa: E402
from agents.experiments.diag_labels import Args, run  # noqa: E402

if __name__ == "__main__":
    main(Args, run, outputs=("json", "plot"))

"""One-step prediction error on held-out data vs episodes, with and without re-normalization
(experiments.measure_renormalization).

    python scripts/measure_renormalization.py --episodes 12 --seeds 0 1 2
"""

import _bootstrap  # noqa: F401

from experiments.measure_renormalization import Args, run
from mbtsr.cli import main

if __name__ == "__main__":
    main(Args, run, outputs=("json",))

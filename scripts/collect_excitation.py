"""Collect excitation data from the two-link arm and plot it (experiments.collect_excitation).

    python scripts/collect_excitation.py                       # defaults: 5 x 200 steps
    python scripts/collect_excitation.py --preset paper --n-traj 10 --out runs/paper_data
"""

import _bootstrap  # noqa: F401

from experiments.collect_excitation import Args, run
from mbtsr.cli import main

if __name__ == "__main__":
    main(Args, run, folders=("out",))

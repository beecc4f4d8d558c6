"""The command line of experiments.ilqr_with_model (``--help`` lists the options)."""

import _bootstrap  # noqa: F401

from experiments.ilqr_with_model import Args, run
from mbtsr.cli import main

if __name__ == "__main__":
    main(Args, run, folders=("out",))

"""The command line of experiments.bench_ilqr (``--help`` lists the options)."""

import _bootstrap  # noqa: F401

from experiments.bench_ilqr import Args, run
from mbtsr.cli import main

if __name__ == "__main__":
    main(Args, run, outputs=("json",))

"""The command line of experiments.exp_deviations (``--help`` lists the options)."""

import _bootstrap  # noqa: F401

from experiments.exp_deviations import cli

if __name__ == "__main__":
    cli()

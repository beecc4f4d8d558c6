"""The command line of experiments.exp_regime (``--help`` lists the options)."""

import _bootstrap  # noqa: F401

from experiments.exp_regime import cli

if __name__ == "__main__":
    cli()

"""The command line of experiments.exp_linear (``--help`` lists the options)."""

import _bootstrap  # noqa: F401

from experiments.exp_linear import cli

if __name__ == "__main__":
    cli()

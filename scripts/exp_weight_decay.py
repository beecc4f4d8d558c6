"""The command line of experiments.exp_weight_decay (``--help`` lists the options)."""

import _bootstrap  # noqa: F401

from experiments.exp_weight_decay import cli

if __name__ == "__main__":
    cli()

"""The command line of experiments.exp_activations (``--help`` lists the options)."""

import _bootstrap  # noqa: F401

from experiments.exp_activations import cli

if __name__ == "__main__":
    cli()

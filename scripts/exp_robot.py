"""The command line of experiments.exp_robot (``--help`` lists the options)."""

import _bootstrap  # noqa: F401

from experiments.exp_robot import cli

if __name__ == "__main__":
    cli()

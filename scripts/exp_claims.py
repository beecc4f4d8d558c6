"""The command line of experiments.exp_claims (``--help`` lists the options)."""

import _bootstrap  # noqa: F401

from experiments.exp_claims import cli

if __name__ == "__main__":
    cli()

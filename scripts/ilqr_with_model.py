"""The command line of agents.experiments.ilqr_with_model (``--help`` lists the options)."""


from agents.experiments.ilqr_with_model import Args, run
from mbtsr.cli import main

if __name__ == "__main__":
    main(Args, run, folders=("out",))

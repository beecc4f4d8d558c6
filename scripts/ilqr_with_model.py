"""The command line of agents.experiments.ilqr_with_model (``--help`` lists the options)."""


from agents.cli import main
from agents.experiments.ilqr_with_model import Args, run

if __name__ == "__main__":
    main(Args, run, folders=("out",))

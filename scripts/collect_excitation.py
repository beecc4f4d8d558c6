"""Collect excitation data from the two-link arm and plot it
(agents.experiments.collect_excitation).

    python scripts/collect_excitation.py                       # defaults: 5 x 200 steps
    python scripts/collect_excitation.py --preset paper --n-traj 10 --out runs/paper_data
"""


from agents.cli import main
from agents.experiments.collect_excitation import Args, run

if __name__ == "__main__":
    main(Args, run, folders=("out",))

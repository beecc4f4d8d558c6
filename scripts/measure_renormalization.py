"""One-step prediction error on held-out data vs episodes, with and without re-normalization
(agents.experiments.measure_renormalization).

    python scripts/measure_renormalization.py --episodes 12 --seeds 0 1 2
"""


from agents.experiments.measure_renormalization import Args, run
from mbtsr.cli import main

if __name__ == "__main__":
    main(Args, run, outputs=("json",))

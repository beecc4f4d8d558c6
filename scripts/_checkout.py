"""What every ``scripts/X.py`` runs: ``python -m agents.experiments.X`` from this checkout."""

import runpy
import sys
from pathlib import Path


def run(script: str) -> None:
    """Run ``agents.experiments.<the script's name>`` as ``__main__``, this checkout's packages
    first on ``sys.path`` (no install or ``PYTHONPATH`` needed).

    :param script: the wrapper's ``__file__``.
    """
    sys.path.insert(0, str(Path(script).resolve().parents[1]))
    runpy.run_module(f"agents.experiments.{Path(script).stem}", run_name="__main__",
                     alter_sys=True)

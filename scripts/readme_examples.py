"""Runs ``python -m agents.experiments.<this file's name>`` from a checkout (``--help``)."""

import runpy
import sys
from pathlib import Path

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's packages
    runpy.run_module(f"agents.experiments.{Path(__file__).stem}", run_name="__main__",
                     alter_sys=True)

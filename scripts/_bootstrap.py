"""Makes ``experiments/`` importable when a script runs from a checkout whose editable install
predates that package (``pip install -e .`` makes this a no-op): appends the repo to sys.path."""

import sys
from pathlib import Path

REPO = str(Path(__file__).resolve().parents[1])
if REPO not in sys.path:
    sys.path.append(REPO)

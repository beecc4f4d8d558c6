"""mbrl-lib's PETS as a peer on the suite's tasks (logic: agents/experiments/pets_peer.py).

It must run in the PETS venv (mbrl 0.2.0's pins clash with this project's): build it once with
``python scripts/setup_pets_venv.py``; this script then re-executes itself with
``.venv-pets/bin/python`` when mbrl is not importable. ``--report-only`` (figures and table from
the JSON) and ``--help`` run in the main environment::

    python scripts/setup_pets_venv.py                                   # ~1.5 min, once
    nice -n 10 python scripts/pets_peer.py --tasks reacher --seeds 0 1 2 --resume
    python scripts/pets_peer.py --report-only
"""

import importlib.util
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
VENV_PYTHON = REPO / ".venv-pets" / "bin" / "python"


def _needs_venv(argv: list[str]) -> bool:
    return not ({"--report-only", "-h", "--help"} & set(argv)) and \
        importlib.util.find_spec("mbrl") is None


if __name__ == "__main__":
    argv = sys.argv[1:]
    if _needs_venv(argv):
        if not VENV_PYTHON.exists():
            sys.exit("mbrl is not importable here and the PETS venv is missing: build it with\n"
                     "    python scripts/setup_pets_venv.py")
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        os.execv(str(VENV_PYTHON), [str(VENV_PYTHON), str(Path(__file__).resolve()), *argv])
    sys.path.insert(0, str(REPO))
    from agents.experiments.pets_peer import main

    sys.exit(main(argv))

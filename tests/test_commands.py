"""Every experiment module is a command: ``python -m agents.experiments.X --help`` exits 0 and
lists the shared flags ``--out`` (where results go) and ``--smoke`` (the tiny CI size); every
``scripts/X.py`` is a thin wrapper of one of them; the console scripts point at functions."""

from __future__ import annotations

import importlib
import json
import os
import re
import runpy
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXPERIMENTS = REPO / "agents" / "experiments"
#: modules of agents/experiments that are libraries of the commands, not commands
LIBRARIES = {"__init__", "paper_common", "peers_crocoddyl"}
COMMANDS = sorted(p.stem for p in EXPERIMENTS.glob("*.py")
                  if p.stem not in LIBRARIES)


@pytest.mark.parametrize("name", COMMANDS)
def test_every_experiment_module_answers_help_with_the_shared_flags(name, monkeypatch, capsys):
    """``python -m agents.experiments.<name> --help``, run in this process as ``-m`` runs it
    (``runpy``, ``__main__``; one real process: :func:`test_a_script_runs_its_module_...`)."""
    monkeypatch.setattr(sys, "argv", [f"{name}.py", "--help"])
    with pytest.raises(SystemExit) as exit_, warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the module was imported before
        runpy.run_module(f"agents.experiments.{name}", run_name="__main__", alter_sys=True)
    out = capsys.readouterr().out
    assert exit_.value.code in (0, None) and out.startswith(f"usage: {name}.py"), out[-2000:]
    assert "--out" in out and "--smoke" in out, out[-2000:]


def test_every_script_is_a_thin_wrapper_of_an_experiment_module():
    scripts = {p.stem for p in (REPO / "scripts").glob("*.py")} - {"_checkout"}
    assert scripts == set(COMMANDS)
    assert "runpy.run_module" in (REPO / "scripts" / "_checkout.py").read_text()
    for name in scripts:
        text = (REPO / "scripts" / f"{name}.py").read_text()
        assert '__import__("_checkout").run(__file__)' in text and len(text.splitlines()) <= 12


def test_a_script_runs_its_module_from_another_folder(tmp_path):
    """The wrapper finds this checkout's packages without an install or PYTHONPATH."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run([sys.executable, str(REPO / "scripts" / "bench_ltv.py"), "--help"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "--smoke" in proc.stdout and proc.stdout.startswith("usage: bench_ltv.py")


def test_console_scripts_name_functions_that_exist():
    text = (REPO / "pyproject.toml").read_text()
    section = text.split("[project.scripts]\n")[1].split("\n\n")[0]
    scripts = dict(re.findall(r'^([\w-]+) = "([\w.:]+)"$', section, flags=re.M))
    assert {"mbtsr-train", "mbtsr-bench"} <= set(scripts), section
    for target in scripts.values():
        module, _, attr = target.partition(":")
        assert callable(getattr(importlib.import_module(module), attr))


@pytest.mark.parametrize("name,out", [("bench_ltv", "r.json"), ("collect_excitation", "folder")])
def test_smoke_runs_end_to_end_and_writes_to_out(name, out, tmp_path, capsys):
    """``--smoke`` (the module's SMOKE values) runs the command in seconds and ``--out`` is
    where its results land (a JSON file or a folder)."""
    module = importlib.import_module(f"agents.experiments.{name}")
    path = tmp_path / out
    result = module.main(["--smoke", "--out", str(path)])
    assert result is not None and path.exists()
    if path.suffix == ".json":
        assert json.loads(path.read_text())["config"]["smoke"] is True
    else:
        assert any(path.iterdir())
    args = module.Args(**{k: v for k, v in module.SMOKE.items()})
    assert args.smoke and all(getattr(args, k) == v for k, v in module.SMOKE.items())

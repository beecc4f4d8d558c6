"""Exact resume after SIGKILL: a run of ``scripts/train_agent.py`` that is killed (twice, at
different moments) and resumed with ``--resume`` ends bit-identical to an uninterrupted run with
the same seed: the same per-episode log (all non-timing columns), the same data, the same model
weights, the same Adam state and the same RNG state.

Real subprocesses, a real ``SIGKILL``; a tiny configuration so that the whole test takes
seconds; torch single-threaded for determinism.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.checkpoint import load_checkpoint
from agents.episode_log import TIMING_COLUMNS
from mbtsr.ensemble import load_model
from mbtsr.trajectory import load_trajectories

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "train_agent.py"
EPISODES = 8
TINY = [
    "--episodes", str(EPISODES), "--seed", "4", "--collection.episode-steps", "25",
    "--collection.n-excitation-episodes", "1", "--training.steps", "20",
    "--training.batch", "32", "--model.ensemble-size", "2", "--model.hidden-width", "12",
    "--planner.horizon", "6", "--planner.ilqr-iterations", "1",
    "--planner.first-plan-iterations", "4", "--regularization.ltv-lambda", "None",
    "--evaluation.every", "2", "--evaluation.episodes", "1", "--evaluation.no-early-exit",
    "--evaluation.no-stop-when-solved", "--evaluation.oracle-cache-dir", "none",
    "--torch-threads", "1", "--no-progress", "--no-plots", "--no-summary-table",
    "--no-tensorboard",
]


def _env() -> dict:
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "MUJOCO_GL": "egl",
            "PYTHONHASHSEED": "0"}


def _start(run_dir: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, str(SCRIPT), "--run-dir", str(run_dir), *TINY, *extra],
        cwd=REPO, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )


def _episodes_in_checkpoint(run_dir: Path) -> int:
    try:
        return int(load_checkpoint(run_dir / "checkpoint.pt")["episodes_done"])
    except (FileNotFoundError, ValueError, RuntimeError, EOFError):
        return 0


def _kill_after(proc: subprocess.Popen, run_dir: Path, episodes: int, delay: float) -> int:
    """SIGKILL ``proc`` ``delay`` seconds after its checkpoint holds ``episodes`` episodes;
    return the number of episodes in the checkpoint right after the kill."""
    deadline = time.monotonic() + 120
    while _episodes_in_checkpoint(run_dir) < episodes:
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        assert time.monotonic() < deadline, "the run made no progress"
        time.sleep(0.02)
    time.sleep(delay)
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait(30) == -signal.SIGKILL
    return _episodes_in_checkpoint(run_dir)


def _finish(proc: subprocess.Popen) -> None:
    _, err = proc.communicate(timeout=240)
    assert proc.returncode == 0, err.decode()[-3000:]


def _rows(run_dir: Path) -> list[dict]:
    with open(run_dir / "episodes.csv") as fh:
        return [{k: v for k, v in r.items() if k not in TIMING_COLUMNS}
                for r in csv.DictReader(fh)]


def _assert_same_tree(a, b, where: str = "") -> None:
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype, where
        assert torch.equal(a, b), f"tensors differ at {where}"
    elif isinstance(a, dict):
        assert set(a) == set(b), where
        for k in a:
            _assert_same_tree(a[k], b[k], f"{where}/{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_same_tree(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def test_sigkill_and_resume_is_bit_identical_to_an_uninterrupted_run(tmp_path):
    straight, killed = tmp_path / "straight", tmp_path / "killed"
    uninterrupted = _start(straight)
    interrupted = _start(killed)
    # kill 1: in episode 3 (0.05 s after episode 2's checkpoint; on a quiet machine an episode
    # of this tiny run takes about a tenth of a second, so EPISODES leaves room for both kills)
    done = _kill_after(interrupted, killed, 2, delay=0.05)
    assert 2 <= done < EPISODES
    # kill 2: right after the resumed run's next checkpoint, possibly while it is still writing
    # the CSV and exports that follow the checkpoint
    resumed = _start(killed, "--resume")
    done2 = _kill_after(resumed, killed, done + 1, delay=0.0)
    assert done < done2 < EPISODES
    _finish(_start(killed, "--resume"))
    _finish(uninterrupted)

    assert _rows(killed) == _rows(straight)
    assert len(_rows(straight)) == EPISODES
    a, b = load_checkpoint(straight / "checkpoint.pt"), load_checkpoint(killed / "checkpoint.pt")
    for key in ("model_state", "optimizer_state", "trajectories", "ltv_lambdas", "rng",
                "torch_rng", "episodes_done", "env_steps", "oracle_costs", "eval_targets"):
        _assert_same_tree(a[key], b[key], key)
    pairs = zip(load_trajectories(straight / "data.npz"), load_trajectories(killed / "data.npz"),
                strict=True)
    for x, y in pairs:
        np.testing.assert_array_equal(x.x, y.x)
        np.testing.assert_array_equal(x.u, y.u)
    wa = load_model(straight / "model.pt").state_dict()  # checksummed file format
    wb = load_model(killed / "model.pt").state_dict()
    _assert_same_tree(wa, wb, "model.pt")


def _script():
    from agents.experiments import (
        train_agent,  # the script's logic (scripts/train_agent.py calls it)
    )

    return train_agent


def test_resume_without_a_checkpoint_and_restart_over_one_fail_clearly(tmp_path, capsys):
    script = _script()
    with pytest.raises(SystemExit) as exc:
        script.main(["--run-dir", str(tmp_path / "none"), "--resume"])
    assert exc.value.code == 2 and "no checkpoint" in capsys.readouterr().err
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "checkpoint.pt").write_bytes(b"")
    with pytest.raises(SystemExit) as exc:
        script.main(["--run-dir", str(tmp_path / "run")])
    assert exc.value.code == 2 and "--resume" in capsys.readouterr().err


@pytest.mark.parametrize("flag", [["--episodes", "0"], ["--planner.horizon", "1"],
                                  ["--regularization", "magic"],
                                  ["--regularization.ltv-lambda", "-1"]])
def test_script_rejects_bad_arguments(flag, capsys):
    with pytest.raises(SystemExit) as exc:
        _script().parse(flag)
    assert exc.value.code == 2
    name = flag[0].lstrip("-").replace("-", "_")
    assert name in capsys.readouterr().err


def test_resume_on_a_damaged_checkpoint_or_a_changed_flag_is_one_line(tmp_path, capsys):
    """--resume names the damaged file, or the config field that differs; no traceback."""
    script = _script()
    run = tmp_path / "run"
    tiny = [a if a != str(EPISODES) else "1" for a in TINY] + ["--evaluation.every", "0"]
    script.main(["--run-dir", str(run), *tiny])
    good = (run / "checkpoint.pt").read_bytes()
    with pytest.raises(SystemExit) as exc:
        script.main(["--run-dir", str(run), "--resume", *tiny, "--planner.horizon", "7"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and "--planner.horizon 7 differs" in err
    damaged = bytearray(good)
    damaged[-10] ^= 4
    for data, what in ((bytes(damaged), "is corrupted"), (good[: len(good) // 3], "is truncated")):
        (run / "checkpoint.pt").write_bytes(data)
        with pytest.raises(SystemExit) as exc:
            script.main(["--run-dir", str(run), "--resume", *tiny])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and err.count("\n") == 1, err
        assert f"{run / 'checkpoint.pt'} {what}" in err
    (run / "checkpoint.pt").write_bytes(good)  # intact again: resumes (nothing left to do)
    assert script.main(["--run-dir", str(run), "--resume", *tiny])["episodes_done"] == 1


def test_resume_loads_the_saved_config_and_refuses_a_contradicting_flag(tmp_path, capsys):
    script = _script()
    run_dir = str(tmp_path / "run")
    tiny = [*TINY[2:], "--episodes", "1", "--evaluation.every", "0"]  # one excitation episode
    script.main(["--run-dir", run_dir, *tiny])
    args = script.parse(["--run-dir", run_dir, "--resume", "--episodes", "2"])
    assert args.agent.seed == 4 and args.agent.model.hidden_width == 12  # from the checkpoint
    assert args.agent.run_dir == run_dir and args.episodes == 2
    assert script.parse(["--run-dir", run_dir, "--resume", "--seed", "4"]).agent.seed == 4
    # the same folder spelled with a trailing slash (shell completion) is not a changed flag
    assert script.parse(["--run-dir", run_dir + "/", "--resume"]).agent.run_dir == run_dir
    with pytest.raises(SystemExit) as exc:
        script.parse(["--run-dir", run_dir, "--resume", "--seed", "5"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and "--seed 5 differs" in err
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    # the whole config tree is saved with the run, nested, and loads back
    assert saved["agent"]["seed"] == 4 and saved["agent"]["model"]["hidden_width"] == 12
    from agents.config import AgentConfig

    assert AgentConfig.from_dict(saved["agent"]) == args.agent

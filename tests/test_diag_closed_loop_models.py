"""The closed-loop model diagnostic: its planning errors against direct computations."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.stats import spearmanr

from agents.experiments import diag_closed_loop_models as diag
from agents.experiments.diag_closed_loop_models import Args, planning_errors, run, task_cost
from mbtsr.trajectory import Trajectory, save_trajectories

rng = np.random.default_rng(0)
N_OBS, N_ACT = 10, 2  # Reacher-v5's observation and action
A = np.eye(N_OBS) + 0.05 * rng.normal(size=(N_OBS, N_OBS)) / np.sqrt(N_OBS)
B = 0.1 * rng.normal(size=(N_OBS, N_ACT))


def true_step(x, u):
    return x @ A.T + u @ B.T


def episodes(count: int, T: int = 40, seed: int = 1) -> list[Trajectory]:
    g = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        u = g.uniform(-1, 1, size=(T, N_ACT))
        x = np.zeros((T + 1, N_OBS))
        x[0] = 0.1 * g.normal(size=N_OBS)
        for t in range(T):
            x[t + 1] = true_step(x[t], u[t])
        out.append(Trajectory(x=x, u=u, dt=0.01))
    return out


def quadratic(x, u):
    return np.sum(x**2, -1) + 0.1 * np.sum(u**2, -1)


def test_the_true_model_has_no_error_and_orders_plans_perfectly():
    train, test = episodes(3), episodes(2, seed=2)
    e = planning_errors(true_step, quadratic, train, test, horizon=10, stride=5)
    assert e["median_dim"] == pytest.approx(0, abs=1e-12)
    assert e["cost_err"] == pytest.approx(0, abs=1e-12)
    assert e["cost_rank"] == pytest.approx(1.0)


def test_cost_error_matches_a_window_by_window_rollout():
    train, test = episodes(3), episodes(2, seed=2)
    bias = 0.01 * np.arange(N_OBS)

    def biased(x, u):
        return true_step(x, u) + bias

    H, stride = 8, 4
    e = planning_errors(biased, quadratic, train, test, horizon=H, stride=stride)
    diffs, predicted, true = [], [], []
    for t in test:  # one window at a time, one state at a time
        for s in range(0, len(t.u) - H + 1, stride):
            x, c_model, c_true = t.x[s], 0.0, 0.0
            for k in range(H):
                x = biased(x[None], t.u[s + k][None])[0]
                c_model += quadratic(x, t.u[s + k])
                c_true += quadratic(t.x[s + k + 1], t.u[s + k])
            diffs.append(abs(c_model - c_true))
            predicted.append(c_model)
            true.append(c_true)
    assert e["cost_err"] == pytest.approx(float(np.median(diffs)), rel=1e-12)
    assert e["cost_err"] > 0 and e["median_dim"] > 0
    assert e["cost_rank"] == pytest.approx(spearmanr(predicted, true).statistic, rel=1e-12)
    assert e["cost_rank"] < 1.0
    assert e["cost_true_median"] == pytest.approx(float(np.median(true)), rel=1e-12)


def test_a_model_that_predicts_a_constant_has_no_rank():
    def state_cost(x, u):
        return np.sum(x**2, -1)

    e = planning_errors(lambda x, u: np.zeros_like(x), state_cost, episodes(3),
                        episodes(2, seed=2), horizon=8, stride=4)
    assert np.isnan(e["cost_rank"]) and e["cost_err"] > 0


def test_displacement_scores_match_a_direct_computation():
    train, test = episodes(3), episodes(2, seed=2)
    track, H, stride, move = (2, 5), 8, 4, 0.13  # about half the windows move further

    def half_motion(x, u):  # moves the tracked dimensions half as far as the truth
        out = true_step(x, u)
        out[:, list(track)] = x[:, list(track)] + 0.5 * (out[:, list(track)] - x[:, list(track)])
        return out

    e = planning_errors(half_motion, quadratic, train, test, horizon=H, stride=stride,
                        track=track, move=move)
    d_true, d_pred = [], []
    for t in test:
        for s in range(0, len(t.u) - H + 1, stride):
            x = t.x[s]
            for k in range(H):
                x = half_motion(x[None], t.u[s + k][None])[0]
            d_true.append(t.x[s + H, list(track)] - t.x[s, list(track)])
            d_pred.append(x[list(track)] - t.x[s, list(track)])
    d_true, d_pred = np.array(d_true), np.array(d_pred)
    moved = np.linalg.norm(d_true, axis=1) > move
    assert 0 < e["moved_windows"] == moved.sum() < len(moved)
    assert e["disp_true"] == pytest.approx(np.median(np.linalg.norm(d_true[moved], axis=1)))
    assert e["disp_pred"] == pytest.approx(np.median(np.linalg.norm(d_pred[moved], axis=1)))
    assert e["disp_err"] == pytest.approx(
        np.median(np.linalg.norm(d_pred[moved] - d_true[moved], axis=1)))
    assert 0 < e["disp_pred"] < e["disp_true"] and e["disp_cos"] < 1.0
    exact = planning_errors(true_step, quadratic, train, test, horizon=H, stride=stride,
                            track=track, move=move)
    assert exact["disp_err"] == pytest.approx(0, abs=1e-12)
    assert exact["disp_cos"] == pytest.approx(1.0)
    assert exact["disp_pred"] == pytest.approx(exact["disp_true"])
    assert "disp_err" not in planning_errors(true_step, quadratic, train, test, horizon=H,
                                             stride=stride)
    with pytest.raises(ValueError, match="track: dimensions"):
        planning_errors(true_step, quadratic, train, test, horizon=H, stride=stride,
                        track=(N_OBS,))


def test_too_few_windows_are_refused():
    with pytest.raises(ValueError, match="windows"):
        planning_errors(true_step, quadratic, episodes(2), episodes(1, T=5), horizon=10,
                        stride=5)


def test_task_cost_evaluates_the_tasks_casadi_cost_on_a_batch():
    cost_of, n, m = task_cost("reacher")
    assert (n, m) == (N_OBS, N_ACT)
    x, u = rng.normal(size=(5, n)), rng.normal(size=(5, m))
    # agents.tasks.reacher: the smoothed |fingertip - target| (obs[8:10]) + |a|^2
    expected = np.sqrt(np.sum(x[:, 8:10] ** 2, -1) + 1e-4) + np.sum(u**2, -1)
    assert cost_of(x, u) == pytest.approx(expected, rel=1e-12)


def save_run(folder, trajs):
    folder.mkdir()
    save_trajectories(folder / "data.npz", trajs)  # as the agent's checkpoint stores them


def test_run_writes_every_model_and_refuses_bad_folders(tmp_path, monkeypatch):
    save_run(tmp_path / "run0", episodes(4))
    out = tmp_path / "diag.json"
    args = Args(task="reacher", checkpoints=(str(tmp_path / "run0"),), sizes=("2x8", "7m:2x8"),
                inits=(0, 1), steps=10, test_episodes=1, horizon=10, stride=5, out=str(out))
    writes = []
    write = diag.write_json_atomic
    monkeypatch.setattr(diag, "write_json_atomic",
                        lambda path, obj: (writes.append(len(obj["rows"])), write(path, obj)))
    result = run(args)
    assert writes == [0, 1, 2, 3, 4]  # the coverage at once, then after every model
    stored = json.loads(out.read_text())
    assert [(r["size"], r["init"]) for r in stored["rows"]] == [
        ("2x8", 0), ("2x8", 1), ("7m:2x8", 0), ("7m:2x8", 1)]
    assert stored["rows"] == json.loads(json.dumps(result["rows"]))
    assert all(np.isfinite(r["cost_err"]) and r["steps"] <= 10 for r in stored["rows"])
    whole = run(dataclasses.replace(args, sizes=("2x8",), patience=None, holdout=0.0,
                                    steps=60))  # no early stopping: every model its budget
    assert [(r["steps"], r["n_holdout"], r["stopped_early"]) for r in whole["rows"]] == [
        (60, 0, False), (60, 0, False)]
    assert all(r["n_holdout"] > 0 for r in stored["rows"])  # the default holds 10 % out
    with pytest.raises(ValueError, match="no data.npz"):
        run(Args(task="reacher", checkpoints=(str(tmp_path),), out=str(out)))
    with pytest.raises(ValueError, match="none to train on"):
        run(Args(task="reacher", checkpoints=(str(tmp_path / "run0"),), test_episodes=4,
                 out=str(out)))
    with pytest.raises(ValueError, match="at least one checkpoint"):
        run(Args(task="reacher", out=str(out)))
    with pytest.raises(ValueError, match="out of range for task 'reacher'"):
        run(Args(task="reacher", checkpoints=(str(tmp_path / "run0"),), track=(10,),
                 out=str(out)))
    with pytest.raises(ValueError, match="task 'pusher' has 23 and 7"):
        run(Args(task="pusher", checkpoints=(str(tmp_path / "run0"),), test_episodes=1,
                 out=str(out)))


@pytest.mark.parametrize("bad, match", [
    ({"task": "reacher-v5"}, "task must be one of"),
    ({"horizon": 0}, "horizon must be an integer >= 1"),
    ({"stride": 0}, "stride must be an integer >= 1"),
    ({"test_episodes": -1}, "test_episodes must be an integer >= 1"),
    ({"inits": ()}, "at least one initialisation"),
    ({"move": 0.0}, "move must be a finite number > 0"),
    ({"track": (17, -1)}, "track entries must be an integer >= 0"),
    ({"track": (17, 17)}, "each dimension once"),
    ({"sizes": ("rule", "5m:2x8")}, "sizes: '5m:2x8'"),
    ({"track": (17, 18), "near": (14,)}, "near needs as many dimensions as track"),
    ({"skip": -1}, "skip must be an integer >= 0"),
    ({"patience": 0}, "patience must be an integer >= 1"),
    ({"holdout": 1.0}, "holdout must be in"),
    ({"holdout": True}, "holdout must be in"),
    ({"holdout": 0.0}, "patience needs held-out data"),
])
def test_bad_arguments_are_refused_before_any_work(bad, match):
    with pytest.raises(ValueError, match=match):
        Args(**bad)


def test_a_task_modelled_on_a_state_fn_is_refused():
    with pytest.raises(ValueError, match="state_fn"):
        task_cost("inverted-double-pendulum")


def test_coverage_counts_the_episodes_that_moved_and_the_closest_approach(tmp_path):
    """``coverage`` on hand-made episodes: the tracked pair moves (3, 4) (norm 5) in one, 0.5 in
    another, nothing in the third; the 'near' pair starts 2 away and passes within 1; the run
    reports it before any training (no sizes) and skips the first ``skip`` episodes."""
    def episode(shift, closest):
        x = np.zeros((5, N_OBS))
        x[-1, 2:4] = shift
        x[:, 4:6] = x[:, 2:4] + np.array([[2.0, 0], [1.5, 0], [closest, 0], [2.0, 0], [2.0, 0]])
        return Trajectory(x=x, u=np.zeros((4, N_ACT)), dt=0.01)

    trajs = [episode((3.0, 4.0), 1.0), episode((0.3, 0.4), 1.2), episode((0.0, 0.0), 0.5)]
    cov = diag.coverage(trajs, (2, 3), move=1.0, near=(4, 5))
    assert cov["episodes_moved"] == 1 and cov["displacement"] == pytest.approx([5.0, 0.5, 0.0])
    assert cov["median_displacement"] == pytest.approx(0.5)
    assert cov["closest"] == pytest.approx([1.0, 1.2, 0.5]) and cov["closest_near"] == 1.0
    assert "closest_near" not in diag.coverage(trajs, (2, 3), move=1.0)
    folder = tmp_path / "run0"
    folder.mkdir()
    save_trajectories(folder / "data.npz", [episode((9.0, 0.0), 3.0)] + trajs)
    out = tmp_path / "c.json"
    result = run(Args(task="reacher", checkpoints=(str(folder),), sizes=(), track=(2, 3),
                      near=(4, 5), move=1.0, skip=1, test_episodes=9, out=str(out)))
    got = result["coverage"][str(folder)]
    assert got == cov and result["rows"] == []
    assert json.loads(out.read_text())["coverage"][str(folder)] == json.loads(json.dumps(cov))
    with pytest.raises(ValueError, match="--skip 4 leaves none for the coverage"):
        run(Args(task="reacher", checkpoints=(str(folder),), sizes=(), track=(2, 3), skip=4,
                 out=str(out)))
    with pytest.raises(ValueError, match="nothing to do"):
        run(Args(task="reacher", checkpoints=(str(folder),), sizes=(), out=str(out)))

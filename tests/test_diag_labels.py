"""The label diagnostic: its replay, its error split against direct computations, a tiny run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agents.experiments.bench_suite import TASKS
from agents.experiments.diag_labels import Args, directions, replay_states, run, split_errors
from agents.experiments.exp_small_data import true_jacobians
from mbtsr.trajectory import Trajectory


def reacher_episode(seed: int = 3, T: int = 12) -> tuple[Trajectory, np.ndarray]:
    env = TASKS["reacher"]["task"].make_env()
    obs, _ = env.reset(seed=seed)
    u = np.random.default_rng(seed).uniform(-1, 1, size=(T, 2))
    xs, states = [obs], []
    for a in u:
        states.append(np.concatenate([env.unwrapped.data.qpos, env.unwrapped.data.qvel]))
        obs, *_ = env.step(a)
        xs.append(obs)
    env.close()
    return Trajectory(np.array(xs), u, 0.02, meta={"seed": seed}), np.array(states)


def test_replay_reproduces_the_states_and_refuses_another_episode():
    traj, states = reacher_episode()
    env = TASKS["reacher"]["task"].make_env()
    assert np.array_equal(replay_states(env, traj, lambda o: o), states)
    other = Trajectory(traj.x, traj.u, traj.dt, meta={"seed": 4})
    with pytest.raises(ValueError, match="leaves the recorded states at step 0"):
        replay_states(env, other, lambda o: o)


def test_reachers_target_is_the_unidentified_direction():
    _, states = reacher_episode()
    W, U = directions("reacher", states)
    # the target (qpos[2:4]) enters the observation as +target (obs 4, 5) and -target in
    # fingertip - target (obs 8, 9); its velocity is not observed
    expected = np.zeros((10, 2))
    expected[[4, 8], 0] = [1, -1]
    expected[[5, 9], 1] = [1, -1]
    expected /= np.sqrt(2)
    assert W.shape == (len(states), 10, 4)  # the arm's two angles and two speeds
    for Wt, Ut in zip(W, U):
        assert Ut.shape == (10, 2)
        assert Ut @ Ut.T == pytest.approx(expected @ expected.T, abs=1e-6)
        assert Wt.T @ Wt == pytest.approx(np.eye(4), abs=1e-9)
        # the arm's directions are not orthogonal to the target's: fingertip - target mixes them
        assert np.abs(Wt.T @ Ut).max() > 0.05
        assert Wt[[4, 5]] == pytest.approx(0, abs=1e-9)  # the target's own entries never move


def test_split_errors_against_the_truth_and_estimates_wrong_along_one_space():
    traj, states = reacher_episode()
    A, B, P = true_jacobians("reacher", states, traj.u)
    W, U = directions("reacher", states)
    exact = split_errors(A, B, P, W, U, A, B)
    assert exact["all"] == pytest.approx(0, abs=1e-9)
    assert exact["identified"] == pytest.approx(0, abs=1e-9)
    assert exact["unidentified"] == pytest.approx(exact["truth_unidentified"])
    assert exact["truth_unidentified"] == pytest.approx(np.sqrt(2), rel=1e-4)  # A v = v
    # right on the moved directions, anything along the target: identified error 0
    rng = np.random.default_rng(0)
    basis = np.concatenate([W, U], axis=2)  # [T, 10, 6], spans the tangent space
    Y = 5.0 * rng.normal(size=U.shape)
    A_hat = np.concatenate([A @ W, Y], axis=2) @ np.linalg.pinv(basis)
    e = split_errors(A, B, P, W, U, A_hat, B)
    assert e["identified"] == pytest.approx(0, abs=1e-9)
    assert e["all"] > 1.0
    assert e["unidentified"] == pytest.approx(np.median(np.linalg.norm(Y, axis=(1, 2))))
    # wrong on the moved directions, by a known amount: the closed form
    E = 0.1 * rng.normal(size=A.shape)
    f = split_errors(A, B, P, W, U, A + E @ P, 2 * B)
    num = np.sqrt(np.sum((E @ P @ W) ** 2, (1, 2)) + np.sum(B**2, (1, 2)))
    den = np.sqrt(np.sum((A @ W) ** 2, (1, 2)) + np.sum(B**2, (1, 2)))
    assert f["identified"] == pytest.approx(np.median(num / den), rel=1e-12)
    with pytest.raises(ValueError, match="A_hat has shape"):
        split_errors(A, B, P, W, U, A_hat[:1], B)


def test_a_tiny_run_records_every_episode(tmp_path):
    out = tmp_path / "labels.json"
    png = tmp_path / "labels.png"
    result = run(Args(task="reacher", regularizations=("none", "exact"), env_steps=100,
                      out=str(out), plot=str(png), smoke=True))
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    stored = json.loads(out.read_text())
    assert stored["summary"] == result["summary"]
    for reg in ("none", "exact"):
        rows = stored["runs"][reg]
        assert [r["env_steps"] for r in rows] == [50, 100]
        assert "model_before" in rows[1] and "model_before" not in rows[0]
        assert ("label" in rows[0]) == (reg == "exact")
        for r in rows:
            assert r["model"]["truth_unidentified"] == pytest.approx(np.sqrt(2), rel=1e-3)
    # the first episode's fit at the same lambda is the same smooth fit in both runs
    assert stored["runs"]["none"][0]["fit"] == stored["runs"]["exact"][0]["fit"]


@pytest.mark.parametrize("bad, match", [
    ({"task": "reacher-v5"}, "task must be one of"),
    ({"regularizations": ("l2",)}, "regularizations must be some of"),
    ({"regularizations": ()}, "regularizations must be some of"),
    ({"env_steps": 1}, "env_steps must be an integer >= 2"),
    ({"task": "arm-far"}, "needs a MuJoCo task of agents.tasks"),
    ({"task": "inverted-double-pendulum"}, "needs a MuJoCo task of agents.tasks"),
])
def test_bad_arguments_are_refused(bad, match):
    with pytest.raises(ValueError, match=match):
        Args(**bad)

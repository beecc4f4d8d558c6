"""The small-data study (agents.experiments.exp_small_data): the true Jacobians against finite
differences of the true step, the Jacobian error metric, wins/total, and a smoke run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agents.experiments.bench_model_sizes import collect
from agents.experiments.exp_small_data import (
    SMOKE,
    Args,
    aggregate,
    jacobian_rel_error,
    run,
    true_jacobians,
    wins_total,
)
from agents.tasks import make_task


@pytest.mark.parametrize("task", ["reacher", "inverted-double-pendulum"])
def test_true_jacobians_match_finite_differences_of_the_true_step(task):
    """``A C(x) dx`` and ``B du`` against centred differences of ``x -> observation(f(x, u))``
    along tangent directions (Reacher: a redundant observation, cos/sin and positions)."""
    from envs.mujoco_model import MujocoDynamics, ObservedDynamics

    test = collect(task, 40, 3, episode_steps=40, states=True)
    x = np.concatenate([t.meta["state"][:-1] for t in test])[5:9]
    u = np.concatenate([t.u for t in test])[5:9]
    A, B, P = true_jacobians(task, x, u)
    env = make_task(task).make_env()
    env.reset(seed=0)
    od = ObservedDynamics(MujocoDynamics(env), env)
    n, d = od.n, od.obs_dim
    assert A.shape == (4, d, d) and B.shape == (4, d, od.action_dim) and P.shape == (4, d, d)

    def next_obs(xx, uu):
        return od.step(np.concatenate([xx, np.zeros(d)]), uu)[n:]

    C = od.observation_jacobian(x)
    rng = np.random.default_rng(0)
    eps = 1e-5
    for i in range(len(x)):
        dx = np.linalg.pinv(C[i], rcond=1e-8) @ C[i] @ rng.normal(size=n)  # observed directions
        du = 0.1 * rng.normal(size=od.action_dim)
        fd_x = (next_obs(x[i] + eps * dx, u[i]) - next_obs(x[i] - eps * dx, u[i])) / (2 * eps)
        fd_u = (next_obs(x[i], u[i] + eps * du) - next_obs(x[i], u[i] - eps * du)) / (2 * eps)
        np.testing.assert_allclose(A[i] @ (C[i] @ dx), fd_x, rtol=1e-6,
                                   atol=1e-6 * np.abs(fd_x).max())
        np.testing.assert_allclose(B[i] @ du, fd_u, rtol=1e-6, atol=1e-6 * np.abs(fd_u).max())
        np.testing.assert_allclose(P[i] @ P[i], P[i], atol=1e-8)  # a projector
    env.close()


def test_jacobian_error_is_zero_for_the_truth_and_matches_a_hand_computation():
    rng = np.random.default_rng(1)
    T, d, m = 3, 4, 2
    A, B = rng.normal(size=(T, d, d)), rng.normal(size=(T, d, m))
    P = np.broadcast_to(np.eye(d), (T, d, d))
    zero = jacobian_rel_error(A, B, P, A.copy(), B.copy())
    assert all(v == pytest.approx(0.0, abs=1e-14) for v in zero.values())
    # perturb one entry of A at point 0 by delta: per-point errors [delta / ||J_0||, 0, 0]
    delta = 0.3
    A_hat = A.copy()
    A_hat[0, 1, 2] += delta
    e = jacobian_rel_error(A, B, P, A_hat, B)
    norms = np.sqrt(np.sum(A**2, (1, 2)) + np.sum(B**2, (1, 2)))
    assert e["jac_rel"] == pytest.approx(np.median([delta / norms[0], 0.0, 0.0]))  # = 0
    assert e["jac_rel_pooled"] == pytest.approx(delta / np.sqrt(np.sum(norms**2)))
    # the same perturbation at every point: median = mean of the per-point ratios' middle one
    A_all = A.copy()
    A_all[:, 1, 2] += delta
    assert jacobian_rel_error(A, B, P, A_all, B)["jac_rel"] == pytest.approx(
        np.median(delta / norms))
    # directions off the tangent space are not compared: P kills the first coordinate
    P0 = np.broadcast_to(np.diag([0.0, 1, 1, 1]), (T, d, d))
    A_t = A @ P0
    A_off = A_t.copy()
    A_off[:, :, 0] += 5.0  # the model's column for the unobserved direction is arbitrary
    assert jacobian_rel_error(A_t, B, P0, A_off, B)["jac_rel"] == pytest.approx(0.0, abs=1e-14)


def test_wins_total_counts_strict_wins_on_common_seeds():
    method = {0: 1.0, 1: 2.0, 2: 3.0, 3: 0.5}
    none = {0: 1.5, 1: 2.0, 2: 2.0, 4: 9.0}
    assert wins_total(method, none) == (1, 3)  # seed 0 wins, 1 ties, 2 loses; 3, 4 unpaired
    recs = [{"task": "t", "episodes": 1, "seed": s, "reg": reg, "transitions": 10,
             "rel_step": v, "jac_rel": v}
            for reg, vals in (("none", [1.0, 1.0, 1.0]), ("sampled", [0.5, 2.0, 0.9]))
            for s, v in enumerate(vals)]
    (cell,) = aggregate(recs, ["none", "sampled"])
    assert cell["jac_rel_sampled_wins"] == [2, 3]
    assert cell["jac_rel_sampled_over_none"] == pytest.approx(0.9)
    assert cell["rel_step"] == {"none": 1.0, "sampled": 0.9}


def test_smoke_run_writes_the_json_with_equal_optimizer_steps(tmp_path):
    out = tmp_path / "small.json"
    args = Args(**{**SMOKE, "out": str(out), "plot": str(tmp_path / "small.png")})
    run(args)
    d = json.loads(out.read_text())
    for key in ("args", "model", "data", "records", "aggregate", "table_markdown", "wall_s"):
        assert key in d
    recs = d["records"]
    assert {r["reg"] for r in recs} == {"none", "sampled", "exact"}
    assert {r["episodes"] for r in recs} == {1, 2}
    assert {r["optimizer_steps"] for r in recs} == {SMOKE["steps"]}
    for r in recs:
        assert np.isfinite(r["jac_rel"]) and np.isfinite(r["rel_step"]) and r["jac_rel"] > 0
    # the first 2 episodes contain the first one
    lengths = d["data"]["inverted-pendulum"]["0"]["episode_lengths"]
    assert {r["transitions"] for r in recs} == {lengths[0], lengths[0] + lengths[1]}
    cell = d["aggregate"][0]
    assert set(cell["jac_rel"]) == {"none", "sampled", "exact"}
    assert cell["jac_rel_exact_wins"][1] == 1
    assert (tmp_path / "small.png").stat().st_size > 0


def test_label_study_and_states_leave_the_data_unchanged(tmp_path):
    plain = collect("reacher", 60, 2, episode_steps=30)
    with_states = collect("reacher", 60, 2, episode_steps=30, states=True)
    for a, b in zip(plain, with_states, strict=True):
        np.testing.assert_array_equal(a.x, b.x)
        np.testing.assert_array_equal(a.u, b.u)
        assert b.meta["state"].shape == (b.T + 1, 8)  # Reacher: nq = nv = 4
    out = tmp_path / "labels.json"
    d = run(Args(**{**SMOKE, "study": "labels", "out": str(out)}))
    assert len(d["records"]) == 2 and set(d["median_jac_rel"]) == {"inverted-pendulum 1",
                                                                   "inverted-pendulum 2"}
    assert all(np.isfinite(r["jac_rel"]) for r in d["records"]) and out.exists()

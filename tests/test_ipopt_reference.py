"""Tests of mbtsr.ipopt_reference and of iLQR against it on the analytic two-link arm."""

from __future__ import annotations

import casadi as ca
import gymnasium as gym
import numpy as np
import pytest

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from mbtsr.costs import quadratic_cost
from mbtsr.ilqr import ilqr
from mbtsr.ipopt_reference import solve_ipopt


def _linear_step(A, B):
    x, u = ca.SX.sym("x", A.shape[0]), ca.SX.sym("u", B.shape[1])
    return ca.Function("lin", [x, u], [ca.mtimes(A, x) + ca.mtimes(B, u)])


def _riccati_controls(A, B, Q, R, Qf, x0, T):
    P, gains = Qf, []
    for _ in range(T):
        K = -np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        gains.append(K)
        P = Q + A.T @ P @ (A + B @ K)
    x, U = x0, []
    for K in reversed(gains):
        U.append(K @ x)
        x = A @ x + B @ U[-1]
    return np.array(U)


def test_unconstrained_lq_matches_riccati():
    rng = np.random.default_rng(0)
    S = rng.standard_normal((3, 3))
    A, B = np.eye(3) + 0.1 * (S - S.T), 0.3 * rng.standard_normal((3, 2))
    Q, R, Qf = np.eye(3), 0.1 * np.eye(2), 4 * np.eye(3)
    x0, T = np.array([1.0, -1.0, 0.5]), 20
    res = solve_ipopt(
        _linear_step(A, B), quadratic_cost(Q, R, np.zeros(3), Qf=Qf), x0, T, None, None
    )
    assert res.success
    np.testing.assert_allclose(res.U, _riccati_controls(A, B, Q, R, Qf, x0, T), atol=1e-7)
    np.testing.assert_allclose(res.X, res.X_sim, atol=1e-8)  # dynamics constraints hold


@pytest.fixture(scope="module")
def arm():
    env = gym.make("mbtsr/TwoLinkArm-v0").unwrapped
    return env.analytic_model(), env.cost_Q, env.cost_R


@pytest.mark.parametrize(
    "x0, target",
    [
        ([0.0, 0.0, 0.0, 0.0], [1.2, -0.8]),
        ([0.3, -0.2, 0.0, 0.0], [-1.0, 1.4]),
        ([-0.4, 0.5, 0.5, -0.5], [0.6, 0.9]),
    ],
)
def test_ilqr_reaches_ipopt_cost_on_the_analytic_arm(arm, x0, target):
    model, Q, R = arm
    x0 = np.asarray(x0)
    cost = quadratic_cost(Q, R, np.r_[target, 0.0, 0.0])
    T = 50
    ref = solve_ipopt(model.casadi_step, cost, x0, T, -1.0, 1.0)
    res = ilqr(cost, model, x0, np.zeros((T, 2)), u_min=-1.0, u_max=1.0)
    assert ref.success, ref.status
    assert res.status == "converged", res.message
    assert np.all(res.U >= -1.0) and np.all(res.U <= 1.0)
    assert np.all(ref.U >= -1.0) and np.all(ref.U <= 1.0)
    assert res.cost <= 1.01 * ref.cost, (res.cost, ref.cost)
    # the reported cost is the cost of the returned controls under the model
    X = np.empty((T + 1, 4))
    X[0] = x0
    for t in range(T):
        X[t + 1] = model.step(X[t], res.U[t])
    assert cost.total(X, res.U) == pytest.approx(res.cost, rel=1e-10)


def test_ipopt_respects_time_offset_of_the_cost():
    """A time-indexed reference: solving from t0 equals solving the shifted reference from 0."""
    A, B = np.array([[1.0, 0.1], [0.0, 1.0]]), np.array([[0.0], [0.1]])
    ref = np.stack([np.sin(0.3 * np.arange(40)), np.zeros(40)], axis=1)
    step = _linear_step(A, B)
    shifted = solve_ipopt(
        step, quadratic_cost(np.eye(2), 0.1 * np.eye(1), ref), np.zeros(2), 15, -2.0, 2.0, t0=10
    )
    direct = solve_ipopt(
        step, quadratic_cost(np.eye(2), 0.1 * np.eye(1), ref[10:]), np.zeros(2), 15, -2.0, 2.0
    )
    np.testing.assert_allclose(shifted.U, direct.U, atol=1e-8)
    assert shifted.cost == pytest.approx(direct.cost, rel=1e-10)


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        ({"T": 0}, ValueError, "T must be an integer >= 1"),
        ({"u_min": 1.0, "u_max": -1.0}, ValueError, "u_min must be <= u_max"),
        ({"x0": np.zeros(3)}, ValueError, r"x0 must have shape \[2\]"),
        ({"U0": np.zeros((4, 1))}, ValueError, r"U0 must have shape \[5, 1\]"),
        ({"casadi_step": _linear_step(np.eye(3), np.ones((3, 1)))}, ValueError, "casadi_step"),
        ({"casadi_step": lambda x, u: x}, TypeError, "casadi.Function"),
        ({"t0": -2}, ValueError, "t0 must be"),
    ],
)
def test_bad_input(kwargs, exc, match):
    args = {
        "casadi_step": _linear_step(np.eye(2), np.ones((2, 1))),
        "cost": quadratic_cost(np.eye(2), np.eye(1), np.zeros(2)),
        "x0": np.zeros(2),
        "T": 5,
        "u_min": -1.0,
        "u_max": 1.0,
    } | kwargs
    with pytest.raises(exc, match=match):
        solve_ipopt(**args)

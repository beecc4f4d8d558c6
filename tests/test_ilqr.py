"""Tests of mbtsr.ilqr against independent solutions: a finite-horizon Riccati recursion, a
bounded linear least-squares solver (scipy BVLS) on the stacked problem, IPOPT on a nonlinear
pendulum; plus failure handling (NaN / exploding models) and input validation."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lqr_reference import NaNOffNominal, _active_set_guess, _box_qp
from scipy.optimize import lsq_linear

from mbtsr.costs import CasadiCost, quadratic_cost
from mbtsr.dynamics import LinearDynamics
from mbtsr.ilqr import ILQROptions, ilqr
from mbtsr.ipopt_reference import solve_ipopt

N_X, N_U = 4, 2


# ---------------------------------------------------------------------- test systems
def _stable_system(seed: int, n: int = N_X, m: int = N_U):
    rng = np.random.default_rng(seed)
    S = rng.standard_normal((n, n))
    A = np.eye(n) + 0.1 * (S - S.T) - 0.02 * np.eye(n)
    B = 0.2 * rng.standard_normal((n, m))
    return A, B


class TimeVaryingLinear:
    """``x_{t+1} = A_t x_t + B u_t`` with ``A_t = A + 0.05 sin(t) E``; uses the protocol's t."""

    def __init__(self, A, B, E):
        self.A, self.B, self.E = A, B, E
        self.state_dim, self.action_dim = B.shape

    def A_at(self, t):
        return self.A + 0.05 * np.sin(t) * self.E

    def step(self, x, u, t=None):
        return x @ self.A_at(t).T + u @ self.B.T

    def jacobians(self, x, u, t=0):
        T = x.shape[0]
        A = np.stack([self.A_at(t + k) for k in range(T)])
        return A, np.broadcast_to(self.B, (T, *self.B.shape)).copy()


class CountingModel:
    """Wraps a model and records the batch shape of every call."""

    def __init__(self, model):
        self.model = model
        self.state_dim, self.action_dim = model.state_dim, model.action_dim
        self.step_batches: list[tuple] = []
        self.jacobian_lengths: list[int] = []

    def step(self, x, u, t=None):
        self.step_batches.append(x.shape[:-1])
        return self.model.step(x, u, t)

    def jacobians(self, x, u, t=0):
        self.jacobian_lengths.append(x.shape[0])
        return self.model.jacobians(x, u, t)


class CasadiModel:
    """Protocol wrapper around a CasADi one-step function ``F(x, u) -> x_next``."""

    def __init__(self, F: ca.Function):
        self.F = F
        x, u = ca.SX.sym("x", F.size_in(0)[0]), ca.SX.sym("u", F.size_in(1)[0])
        xn = F(x, u)
        self.J = ca.Function("J", [x, u], [ca.jacobian(xn, x), ca.jacobian(xn, u)])
        self.state_dim, self.action_dim = F.size_in(0)[0], F.size_in(1)[0]

    def step(self, x, u, t=None):
        lead = x.shape[:-1]
        xs, us = x.reshape(-1, self.state_dim), u.reshape(-1, self.action_dim)
        out = np.asarray(self.F.map(xs.shape[0])(xs.T, us.T)).T
        return out.reshape(*lead, self.state_dim)

    def jacobians(self, x, u, t=0):
        T, n, m = x.shape[0], self.state_dim, self.action_dim
        A, B = self.J.map(T)(x.T, u.T)
        return (
            np.asarray(A).reshape(n, T, n).transpose(1, 0, 2),
            np.asarray(B).reshape(n, T, m).transpose(1, 0, 2),
        )


def pendulum_step(dt: float = 0.05) -> ca.Function:
    """Damped pendulum, theta = 0 hanging down, RK4 over one step; u = torque."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)

    def f(s):
        return ca.vertcat(s[1], -9.81 * ca.sin(s[0]) - 0.2 * s[1] + 4.0 * u[0])

    k1 = f(x)
    k2 = f(x + dt / 2 * k1)
    k3 = f(x + dt / 2 * k2)
    k4 = f(x + dt * k3)
    return ca.Function("pendulum", [x, u], [x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)])


# ---------------------------------------------------------------------- independent solvers
def _riccati(A_seq, B, Q, R, Qf, x0):
    """Finite-horizon LQR for ``sum x'Qx + u'Ru + x_T'Qf x_T`` (no 1/2), time-varying A_t."""
    T = len(A_seq)
    P, gains = Qf, [None] * T
    for t in range(T - 1, -1, -1):
        A = A_seq[t]
        K = -np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        gains[t] = K
        P = Q + A.T @ P @ (A + B @ K)
    x, U = x0, []
    for t in range(T):
        U.append(gains[t] @ x)
        x = A_seq[t] @ x + B @ U[-1]
    return np.array(U), np.array(gains)


def _stacked_least_squares(A, B, Q, R, Qf, x_goal, x0, T, lower=None, upper=None):
    """Solve the LQ tracking problem as one bounded linear least-squares problem (BVLS).

    ``X = Phi x0 + Gamma U``; cost = sum_t ||Q^1/2 (x_t - g_t)||^2 + ||R^1/2 u_t||^2 + terminal.
    """
    n, m = B.shape
    Phi = np.zeros(((T + 1) * n, n))
    Gamma = np.zeros(((T + 1) * n, T * m))
    Ak = np.eye(n)
    for t in range(T + 1):
        Phi[t * n : (t + 1) * n] = Ak
        Ak = A @ Ak
    for t in range(1, T + 1):
        for s in range(t):
            Gamma[t * n : (t + 1) * n, s * m : (s + 1) * m] = (
                np.linalg.matrix_power(A, t - 1 - s) @ B
            )
    Wx = np.kron(np.eye(T + 1), np.eye(n))
    Lq, Lf, Lr = (np.linalg.cholesky(M + 1e-300 * np.eye(len(M))).T for M in (Q, Qf, R))
    W = np.zeros(((T + 1) * n, (T + 1) * n))
    for t in range(T + 1):
        W[t * n : (t + 1) * n, t * n : (t + 1) * n] = Lf if t == T else Lq
    goal = np.tile(x_goal, T + 1) if x_goal.ndim == 1 else x_goal[: T + 1].ravel()
    M_state = W @ Wx @ Gamma
    b_state = -(W @ (Phi @ x0 - goal))
    M = np.vstack([M_state, np.kron(np.eye(T), Lr)])
    b = np.concatenate([b_state, np.zeros(T * m)])
    lb = -np.inf if lower is None else np.tile(lower, T)
    ub = np.inf if upper is None else np.tile(upper, T)
    sol = lsq_linear(M, b, bounds=(lb, ub), method="bvls", tol=1e-14)
    return sol.x.reshape(T, m)


# ---------------------------------------------------------------------- LQ problems
@pytest.mark.parametrize("reg_type", [1, 2])
def test_one_iteration_gives_the_riccati_solution(reg_type):
    A, B = _stable_system(0)
    Q, R, Qf = np.diag([1.0, 2.0, 0.5, 0.1]), 0.1 * np.eye(N_U), 5 * np.eye(N_X)
    x0 = np.array([1.0, -0.5, 0.3, 0.8])
    T = 40
    res = ilqr(
        quadratic_cost(Q, R, np.zeros(N_X), Qf=Qf),
        LinearDynamics(A, B),
        x0,
        np.zeros((T, N_U)),
        options=ILQROptions(lambda_init=0.0, max_iter=1, reg_type=reg_type),
    )
    U_lqr, K_lqr = _riccati([A] * T, B, Q, R, Qf, x0)
    np.testing.assert_allclose(res.U, U_lqr, atol=1e-10)
    np.testing.assert_allclose(res.K, K_lqr, atol=1e-10)
    assert res.trace[0]["alpha"] == 1.0
    # on an LQ problem the expected improvement is exact
    assert res.trace[0]["actual"] == pytest.approx(res.trace[0]["expected"], rel=1e-9)


def test_time_varying_model_uses_absolute_time():
    A, B = _stable_system(1)
    E = np.random.default_rng(1).standard_normal((N_X, N_X))
    model = TimeVaryingLinear(A, B, E)
    Q, R, Qf = np.eye(N_X), 0.2 * np.eye(N_U), 3 * np.eye(N_X)
    x0, T, t0 = np.array([0.5, 1.0, -1.0, 0.2]), 30, 7
    res = ilqr(
        quadratic_cost(Q, R, np.zeros(N_X), Qf=Qf),
        model,
        x0,
        np.zeros((T, N_U)),
        options=ILQROptions(lambda_init=0.0, max_iter=1),
        t0=t0,
    )
    U_lqr, _ = _riccati([model.A_at(t0 + k) for k in range(T)], B, Q, R, Qf, x0)
    np.testing.assert_allclose(res.U, U_lqr, atol=1e-10)


def test_tracking_a_time_indexed_reference_matches_least_squares():
    A, B = _stable_system(2)
    Q, R, Qf = np.eye(N_X), 0.05 * np.eye(N_U), 2 * np.eye(N_X)
    T = 25
    ref = np.stack([np.sin(0.2 * np.arange(T + 1) + k) for k in range(N_X)], axis=1)
    x0 = np.zeros(N_X)
    res = ilqr(quadratic_cost(Q, R, ref, Qf=Qf), LinearDynamics(A, B), x0, np.zeros((T, N_U)))
    assert res.status == "converged"
    U_ls = _stacked_least_squares(A, B, Q, R, Qf, ref, x0, T)
    np.testing.assert_allclose(res.U, U_ls, atol=1e-6)


@pytest.mark.parametrize("seed", [3, 4])
def test_control_limits_match_bounded_least_squares(seed):
    A, B = _stable_system(seed)
    Q, R, Qf = np.eye(N_X), 0.01 * np.eye(N_U), 10 * np.eye(N_X)
    lower, upper = np.array([-0.6, -0.3]), np.array([0.4, 0.5])
    x0 = np.array([0.5, -0.5, 0.25, 0.4])
    T = 30
    cost = quadratic_cost(Q, R, np.zeros(N_X), Qf=Qf)
    res = ilqr(
        cost,
        LinearDynamics(A, B),
        x0,
        np.zeros((T, N_U)),
        u_min=lower,
        u_max=upper,
        options=ILQROptions(tol_fun=1e-13, tol_grad=1e-10),
    )
    U_ls = _stacked_least_squares(A, B, Q, R, Qf, np.zeros(N_X), x0, T, lower, upper)
    assert res.status == "converged"
    assert np.all(res.U >= lower) and np.all(res.U <= upper)
    active = np.isclose(U_ls, lower) | np.isclose(U_ls, upper)
    assert active.any(), "the test problem should have active limits"
    X_ls = np.vstack([x0, np.zeros((T, N_X))])
    for t in range(T):
        X_ls[t + 1] = A @ X_ls[t] + B @ U_ls[t]
    assert res.cost == pytest.approx(cost.total(X_ls, U_ls), rel=1e-10)
    np.testing.assert_allclose(res.U, U_ls, atol=1e-6)
    # clamped controls get zero feedback rows
    at_bound = (res.U <= lower + 1e-12) | (res.U >= upper - 1e-12)
    assert at_bound.any()
    assert np.all(res.K[at_bound] == 0.0), "clamped dimensions must not get feedback"
    assert np.any(res.K[~at_bound] != 0.0)


# ---------------------------------------------------------------------- box QP
@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    m=st.integers(1, 4),
    scale=st.floats(0.1, 10.0),
)
def test_box_qp_matches_bounded_least_squares(seed, m, scale):
    """min 0.5 x'Hx + g'x over a box == min ||L'x + L^-1 g||^2 (H = L L'), solved by BVLS."""
    rng = np.random.default_rng(seed)
    S = rng.standard_normal((m, m))
    H = S @ S.T + 0.1 * np.eye(m)
    g = scale * rng.standard_normal(m)
    lower = -rng.uniform(0.0, 1.0, m)
    upper = rng.uniform(0.0, 1.0, m)
    L = np.linalg.cholesky(H)
    ref = lsq_linear(L.T, -np.linalg.solve(L, g), bounds=(lower, upper), method="bvls").x
    opts = ILQROptions()
    x, free, ok = _box_qp(H, g, lower, upper, np.zeros(m), opts)
    assert ok
    value = lambda z: 0.5 * z @ H @ z + g @ z  # noqa: E731
    assert value(x) <= value(ref) + 1e-9 * max(1.0, abs(value(ref)))
    assert np.all(x >= lower) and np.all(x <= upper)
    # free dimensions: strictly inside the box -> free; at a bound with the gradient pushing
    # outwards -> clamped
    grad = H @ x + g
    inside = (x > lower + 1e-9) & (x < upper - 1e-9)
    pushing_out = ((x <= lower) & (grad > 1e-9)) | ((x >= upper) & (grad < -1e-9))
    assert np.all(free[inside]) and not np.any(free[pushing_out])
    x_guess, _, ok_guess = _active_set_guess(H, g, -np.linalg.solve(H, g), lower, upper)
    if ok_guess:  # when the cheap guess claims optimality it must be optimal
        assert value(x_guess) <= value(ref) + 1e-9 * max(1.0, abs(value(ref)))


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    lower=st.lists(st.floats(-2.0, 0.0), min_size=2, max_size=2),
    width=st.lists(st.floats(0.0, 2.0), min_size=2, max_size=2),
    scale=st.floats(0.0, 5.0),
)
def test_returned_controls_always_respect_the_box(seed, lower, width, scale):
    """Any box (including zero-width ones) and start: finite controls inside the box, a cost no
    worse than the initial guess's."""
    A, B = _stable_system(seed % 50)
    lower = np.asarray(lower)
    upper = lower + np.asarray(width)
    rng = np.random.default_rng(seed)
    x0 = scale * rng.standard_normal(N_X)
    U0 = rng.uniform(-3, 3, (15, N_U))
    cost = quadratic_cost(np.eye(N_X), 0.1 * np.eye(N_U), np.zeros(N_X))
    model = LinearDynamics(A, B)
    res = ilqr(cost, model, x0, U0, u_min=lower, u_max=upper, options={"max_iter": 50})
    assert np.isfinite(res.U).all()
    assert np.all(res.U >= lower) and np.all(res.U <= upper)
    U_clipped = np.clip(U0, lower, upper)
    X0 = np.vstack([x0, np.zeros((15, N_X))])
    for t in range(15):
        X0[t + 1] = A @ X0[t] + B @ U_clipped[t]
    J0 = cost.total(X0, U_clipped)  # the same rollout in another operation order: rounding
    assert res.cost <= J0 + 1e-12 * max(1.0, abs(J0))
    assert res.status != "failed"


def test_active_set_guess_accepts_exactly_the_optimal_clampings():
    """The cheap guess must claim optimality iff clamping the violated dimensions is optimal
    (checked against BVLS on 400 random box-QPs with m = 1..3, including zero-width boxes)."""
    rng = np.random.default_rng(11)
    n_ok = 0
    for trial in range(400):
        m = 1 + trial % 3
        S = rng.standard_normal((m, m))
        H = S @ S.T + 0.1 * np.eye(m)
        g = 3 * rng.standard_normal(m)
        lower, upper = -rng.uniform(0, 1, m), rng.uniform(0, 1, m)
        if trial % 10 == 0:
            upper[0] = lower[0]
        x_free = -np.linalg.solve(H, g)
        if np.all((x_free >= lower) & (x_free <= upper)):
            continue  # the solver only calls the guess when the box is violated
        L = np.linalg.cholesky(H)
        # (BVLS needs lower < upper: a 1e-12 wide box stands in for a fixed dimension)
        ref = lsq_linear(
            L.T,
            -np.linalg.solve(L, g),
            bounds=(lower, np.maximum(upper, lower + 1e-12)),
            method="bvls",
        ).x
        x, free, ok = _active_set_guess(H, g, x_free, lower, upper)
        guess_is_optimal = np.allclose(x, ref, atol=1e-7) and np.all((x >= lower) & (x <= upper))
        assert ok == guess_is_optimal, (trial, x, ref)
        n_ok += ok
    assert 50 < n_ok  # the guess is right often enough to be worth it


# ---------------------------------------------------------------------- batching
def test_one_batched_rollout_and_one_jacobian_call_per_iteration():
    model = CountingModel(CasadiModel(pendulum_step()))
    cost = quadratic_cost(np.diag([10.0, 0.1]), 0.01 * np.eye(1), np.array([1.0, 0.0]))
    T, iters = 30, 4
    opts = ILQROptions(max_iter=iters, tol_fun=0.0)
    res = ilqr(cost, model, np.zeros(2), np.zeros((T, 1)), options=opts)
    n_forward = sum(1 for tr in res.trace if not np.isnan(tr["expected"]) or tr["accepted"])
    assert res.iterations == iters
    # initial rollout (batch 1) + one rollout of all step sizes per iteration
    assert len(model.step_batches) == T * (1 + n_forward)
    assert model.step_batches[0] == (1,)
    assert all(b == (len(opts.alphas),) for b in model.step_batches[T:])
    n_accepted = sum(tr["accepted"] for tr in res.trace)
    assert len(model.jacobian_lengths) == 1 + min(n_accepted, iters - 1)
    assert all(n == T for n in model.jacobian_lengths)


def test_same_inputs_give_identical_results():
    model = CasadiModel(pendulum_step())
    cost = quadratic_cost(np.diag([10.0, 0.1]), 0.01 * np.eye(1), np.array([2.0, 0.0]))
    a = ilqr(cost, model, np.zeros(2), np.zeros((40, 1)), u_min=-1, u_max=1)
    b = ilqr(cost, model, np.zeros(2), np.zeros((40, 1)), u_min=-1, u_max=1)
    np.testing.assert_array_equal(a.U, b.U)
    assert a.cost == b.cost and a.iterations == b.iterations


# ---------------------------------------------------------------------- nonlinear vs IPOPT
@pytest.mark.parametrize("theta_goal", [1.0, 2.5])
def test_pendulum_matches_ipopt(theta_goal):
    F = pendulum_step()
    cost = quadratic_cost(
        np.diag([10.0, 0.1]),
        0.05 * np.eye(1),
        np.array([theta_goal, 0.0]),
        Qf=np.diag([100.0, 10.0]),
    )
    T, x0 = 60, np.zeros(2)
    res = ilqr(cost, CasadiModel(F), x0, np.zeros((T, 1)), u_min=-1.5, u_max=1.5)
    ref = solve_ipopt(F, cost, x0, T, -1.5, 1.5)
    assert ref.success
    assert res.status == "converged"
    assert np.all(np.abs(res.U) <= 1.5)
    assert res.cost <= 1.01 * ref.cost
    assert np.isfinite(res.K).all()


# ---------------------------------------------------------------------- failure handling
class Exploding(NaNOffNominal):
    """Returns astronomically large (then overflowing) states for non-zero controls."""

    def step(self, x, u, t=None):
        out = self.lin.step(x, u)
        with np.errstate(over="ignore"):
            out[np.any(u != 0, axis=-1)] *= 1e300
        return out


@pytest.mark.parametrize("model_cls", [NaNOffNominal, Exploding])
def test_diverging_model_gives_failed_status_and_finite_best_iterate(model_cls):
    A, B = _stable_system(5)
    T = 20
    cost = quadratic_cost(np.eye(N_X), 0.1 * np.eye(N_U), np.zeros(N_X))
    x0 = np.ones(N_X)
    res = ilqr(cost, model_cls(A, B), x0, np.zeros((T, N_U)), u_min=-1, u_max=1)
    assert res.status == "failed"
    assert "lambda_max" in res.message
    assert np.isfinite(res.U).all() and np.all(res.U == 0.0)  # the best (initial) iterate
    assert np.isfinite(res.X).all() and np.isfinite(res.cost)
    lambdas = [tr["lambda"] for tr in res.trace]
    assert np.all(np.diff(lambdas) > 0) and lambdas[-1] > ILQROptions().lambda_max
    assert not any(tr["accepted"] for tr in res.trace)


def test_nan_jacobians_give_failed_status():
    A, B = _stable_system(6)

    class NaNJacobians(NaNOffNominal):
        def step(self, x, u, t=None):
            return self.lin.step(x, u)

        def jacobians(self, x, u, t=0):
            Aj, Bj = self.lin.jacobians(x, u)
            Aj[3] = np.nan
            return Aj, Bj

    U0 = 0.1 * np.ones((10, N_U))
    res = ilqr(
        quadratic_cost(np.eye(N_X), np.eye(N_U), np.zeros(N_X)),
        NaNJacobians(A, B),
        np.ones(N_X),
        U0,
    )
    assert res.status == "failed" and "non-finite" in res.message
    np.testing.assert_array_equal(res.U, U0)


def test_initial_rollout_divergence_is_reported():
    model = LinearDynamics(1e5 * np.eye(N_X), np.ones((N_X, N_U)))
    res = ilqr(
        quadratic_cost(np.eye(N_X), np.eye(N_U), np.zeros(N_X)),
        model,
        np.ones(N_X),
        np.zeros((10, N_U)),
        u_min=-1,
        u_max=1,
    )
    assert res.status == "failed" and "initial rollout diverged" in res.message
    assert np.isfinite(res.U).all() and res.cost == np.inf


def test_starting_at_the_optimum_converges():
    A, B = _stable_system(7)
    Q, R, Qf = np.eye(N_X), 0.1 * np.eye(N_U), np.eye(N_X)
    x0, T = np.ones(N_X), 20
    U_lqr, _ = _riccati([A] * T, B, Q, R, Qf, x0)
    res = ilqr(quadratic_cost(Q, R, np.zeros(N_X), Qf=Qf), LinearDynamics(A, B), x0, U_lqr)
    assert res.status == "converged"
    np.testing.assert_allclose(res.U, U_lqr, atol=1e-8)


# ---------------------------------------------------------------------- bad input
def _problem():
    A, B = _stable_system(8)
    return quadratic_cost(np.eye(N_X), np.eye(N_U), np.zeros(N_X)), LinearDynamics(A, B)


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        ({"u_min": [0.0, 1.0], "u_max": [1.0, 0.0]}, ValueError, "u_min must be <= u_max"),
        ({"u_min": [0.0, 1.0, 2.0]}, ValueError, r"u_min must be a scalar or have shape \[2\]"),
        ({"u_max": [np.nan, 1.0]}, ValueError, "u_max contains NaN"),
        ({"x0": np.zeros(3)}, ValueError, r"x0 must have shape \[4\]"),
        ({"x0": np.full(4, np.nan)}, ValueError, "x0 contains"),
        ({"U0": np.zeros((5, 3))}, ValueError, r"U0 must have shape \[\*, 2\]"),
        ({"U0": np.zeros((0, 2))}, ValueError, "at least one time step"),
        ({"t0": -1}, ValueError, "t0 must be an integer"),
        ({"options": {"max_iterations": 3}}, ValueError, "unknown ILQROptions"),
        ({"options": 3}, TypeError, "options must be"),
        ({"params": np.zeros(5)}, ValueError, r"params must be \[6\] or \[N_ref, 6\]"),
        ({"params": np.full(6, np.inf)}, ValueError, "params contains 6 non-finite"),
        ({"u_min": "low"}, ValueError, "u_min must be numeric"),
    ],
)
def test_bad_input_raises_clear_errors(kwargs, exc, match):
    cost, model = _problem()
    args = {"x0": np.zeros(N_X), "U0": np.zeros((5, N_U))} | kwargs
    x0, U0 = args.pop("x0"), args.pop("U0")
    with pytest.raises(exc, match=match):
        ilqr(cost, model, x0, U0, **args)


def test_dimension_mismatch_between_cost_and_model():
    cost = quadratic_cost(np.eye(3), np.eye(N_U), np.zeros(3))
    with pytest.raises(ValueError, match="state_dim=4 does not match"):
        ilqr(cost, _problem()[1], np.zeros(3), np.zeros((5, N_U)))
    with pytest.raises(TypeError, match="cost must be"):
        ilqr(lambda x: x, _problem()[1], np.zeros(4), np.zeros((5, N_U)))


@pytest.mark.parametrize(
    "field, value",
    [
        ("alphas", (1.5,)),
        ("alphas", ()),
        ("reg_type", 3),
        ("lambda_factor", 1.0),
        ("max_iter", 0),
        ("tol_fun", -1.0),
        ("lambda_max", 0.0),
    ],
)
def test_invalid_options_are_rejected(field, value):
    with pytest.raises(ValueError, match=field):
        ILQROptions(**{field: value})


def test_params_at_call_time_give_the_solution_of_a_cost_built_for_that_goal():
    A, B = _stable_system(9)
    model = LinearDynamics(A, B)
    Q, R = np.eye(N_X), 0.1 * np.eye(N_U)
    shared = quadratic_cost(Q, R)
    x0, U0 = np.ones(N_X), np.zeros((15, N_U))
    for goal in (np.full(N_X, 0.5), np.array([1.0, -1.0, 0.0, 0.2])):
        a = ilqr(shared, model, x0, U0, params=shared.reference(goal), u_min=-1, u_max=1)
        b = ilqr(quadratic_cost(Q, R, goal), model, x0, U0, u_min=-1, u_max=1)
        np.testing.assert_array_equal(a.U, b.U)
        assert a.cost == b.cost and a.status == b.status == "converged"


def test_a_model_or_cost_that_turns_nan_mid_solve_ends_failed_with_the_best_finite_iterate():
    """The model returns NaN once the state leaves a ball; the cost turns NaN beyond another.
    The solve never returns a NaN control, and its cost is that of the returned iterate."""
    A, B = _stable_system(10)
    x, u = ca.SX.sym("x", N_X), ca.SX.sym("u", N_U)
    nan_cost = CasadiCost.from_expressions(
        x, u, ca.sumsqr(x - 3.0) + ca.sumsqr(u) + ca.sqrt(1.95 - x[0]), ca.sumsqr(x - 3.0)
    )
    for cost in (quadratic_cost(np.eye(N_X), 0.01 * np.eye(N_U), np.full(N_X, 3.0)), nan_cost):
        res = ilqr(cost, NaNOffNominal(A, B, beyond=2.0), np.ones(N_X), np.zeros((10, N_U)),
                   u_min=-2, u_max=2, options={"max_iter": 40})
        assert np.isfinite(res.U).all() and np.all(np.abs(res.U) <= 2.0)
        assert np.isfinite(res.X).all()
        assert res.cost == pytest.approx(cost.total(res.X, res.U), rel=1e-12)


def test_an_all_nan_cost_fails_with_finite_controls_inside_the_box():
    """A cost that is NaN everywhere (e.g. a typo'd expression) cannot be optimised: the solve
    says so (status failed) and still returns the finite, clipped initial guess."""
    A, B = _stable_system(11)
    x, u = ca.SX.sym("x", N_X), ca.SX.sym("u", N_U)
    nan = ca.sqrt(-1.0 - ca.sumsqr(x))  # NaN for every state
    cost = CasadiCost.from_expressions(x, u, nan + ca.sumsqr(u), nan)
    U0 = np.full((8, N_U), 3.0)
    res = ilqr(cost, LinearDynamics(A, B), np.ones(N_X), U0, u_min=-1, u_max=1,
               options={"max_iter": 10})
    assert res.status == "failed"
    assert np.isfinite(res.U).all() and np.all(np.abs(res.U) <= 1.0)
    assert np.isfinite(res.X).all()


@settings(max_examples=25, deadline=None)
@given(
    st.integers(0, 2**16),
    st.sampled_from(["nan_x0", "inf_U0", "short_x0", "bad_bounds", "bad_params", "ok"]),
)
def test_property_bad_input_is_named_good_input_gives_finite_bounded_controls(seed, case):
    rng = np.random.default_rng(seed)
    cost, model = _problem()
    x0, U0 = rng.standard_normal(N_X), rng.standard_normal((6, N_U))
    kw = {"u_min": -0.5, "u_max": 0.5, "options": {"max_iter": 5}}
    i = int(rng.integers(N_X))
    if case == "nan_x0":
        x0[i] = np.nan
        match = f"x0 contains 1 non-finite value.*first at index \\({i},\\)"
    elif case == "inf_U0":
        U0[i % 6, 1] = -np.inf
        match = "U0 contains 1 non-finite"
    elif case == "short_x0":
        x0, match = x0[:-1], "x0 must have shape"
    elif case == "bad_bounds":
        kw["u_min"], match = 1.0, "u_min must be <= u_max"
    elif case == "bad_params":
        kw["params"], match = np.ones(N_X), "params must be"
    if case != "ok":
        with pytest.raises(ValueError, match=match):
            ilqr(cost, model, x0, U0, **kw)
        return
    res = ilqr(cost, model, x0, U0, **kw)
    assert np.isfinite(res.U).all() and np.all(np.abs(res.U) <= 0.5)
    assert res.status in ("converged", "max_iter", "failed")


def test_initial_rollout_through_the_compiled_kernel_equals_stepping():
    """iLQR's first rollout through a model's compiled closed-loop rollout (zero gains) gives
    the states of stepping the model, and falls back to them (NaN after the divergence) when
    the rollout diverges."""
    from mbtsr.dynamics import LinearDynamics, _rollout
    from mbtsr.ilqr import _initial_rollout

    rng = np.random.default_rng(2)
    A, B = np.eye(3) + 0.1 * rng.normal(size=(3, 3)), rng.normal(size=(3, 2))
    model = LinearDynamics(A, B)
    x0, U = rng.normal(size=3), rng.uniform(-1, 1, size=(15, 2))
    X, alive = _initial_rollout(model, x0, U, 0, 1e8)
    want, want_alive = _rollout(model, x0, U[None], 0, 1e8)
    np.testing.assert_allclose(X, want, rtol=1e-14, atol=1e-14)
    assert alive.all() and want_alive.all()
    X, alive = _initial_rollout(LinearDynamics(10 * A, B), x0, U, 0, 1e3)
    assert not alive[0] and np.isnan(X[0, -1]).all() and np.isfinite(X[0, 0]).all()


@pytest.mark.parametrize("max_norm", [1e8, 6.0, 1e-3])
def test_compiled_affine_line_search_rollouts_equal_the_python_rollouts(max_norm):
    """iLQR's closed-loop rollouts of an affine model in one compiled call
    (``rollout_policy_affine``) equal the solver's generic rollouts through ``step`` (same
    states, controls and dead rows), also when rows diverge to non-finite states."""
    from mbtsr.ilqr import _rollout_policy

    rng = np.random.default_rng(5)
    n, m, T = 4, 2, 9
    for scale in (1.0, 1e200):  # 1e200: rows overflow to inf and continue from the nominal
        model = LinearDynamics(scale * (np.eye(n) + 0.3 * rng.normal(size=(n, n))),
                               rng.normal(size=(n, m)))

        class StepOnly:  # the same model seen only through its step: the generic path
            state_dim, action_dim = n, m
            step = staticmethod(model.step)

        X = rng.normal(size=(T + 1, n))
        U, k = rng.normal(size=(T, m)), rng.normal(size=(T, m))
        K = 0.3 * rng.normal(size=(T, m, n))
        alphas = np.array([1.0, 0.5, 0.1, 0.01])
        lower, upper = np.array([-1.0, -np.inf]), np.array([0.5, np.inf])
        with np.errstate(all="ignore"):
            got = _rollout_policy(model, X[0], X, U, k, K, alphas, lower, upper, 0, max_norm)
            want = _rollout_policy(StepOnly(), X[0], X, U, k, K, alphas, lower, upper, 0,
                                   max_norm)
        for g, w in zip(got, want):
            np.testing.assert_allclose(g, w, rtol=1e-13, atol=1e-13)
        if max_norm < 10:
            assert not got[2].all()  # some rows were declared dead, identically

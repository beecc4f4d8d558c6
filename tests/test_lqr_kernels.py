"""The compiled iLQR backward pass (mbtsr._lqr_kernels) against independent computations.

- the numpy reference recursion in mbtsr.ilqr (augmented form, LAPACK) on random problems,
  both regularisation types, with and without box limits (tight tolerance);
- the exact LQ solution of a dense quadratic program (first iteration, lambda = 0, no limits);
- the box QP against scipy's bounded-variable least squares (BVLS);
- the compiled affine closed-loop rollout against the generic (model.step) rollout;
- the chunked line search (``line_search_chunks`` models) against the all-at-once one;
- the compile cache: a fresh process loads the kernel without recompiling.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lqr_reference import _backward_pass, _box_qp, _LQProblem
from scipy.optimize import lsq_linear

from mbtsr import _lqr_kernels as kernels
from mbtsr.costs import quadratic_cost
from mbtsr.dynamics import LINE_SEARCH_CHUNKS, LinearDynamics
from mbtsr.ilqr import ILQROptions, _rollout_policy, ilqr

PRM = kernels.BOXQP_DEFAULTS


def random_problem(T: int, n: int, m: int, seed: int):
    """Random Jacobians, PSD stage/terminal Hessians, PD ``luu``, nominal controls in (-1, 1)."""
    rng = np.random.default_rng(seed)
    A = np.eye(n) + 0.2 * rng.standard_normal((T, n, n))
    B = rng.standard_normal((T, n, m))
    G = rng.standard_normal((T + 1, n, n))
    lxx = G @ G.transpose(0, 2, 1) / n
    G = rng.standard_normal((T, m, m))
    luu = G @ G.transpose(0, 2, 1) / m + 0.1 * np.eye(m)
    derivs = (
        rng.standard_normal((T + 1, n)),
        rng.standard_normal((T, m)),
        lxx,
        luu,
        0.1 * rng.standard_normal((T, m, n)),
    )
    U = rng.uniform(-0.9, 0.9, (T, m))
    return A, B, derivs, U


def run_both(A, B, derivs, U, lower, upper, lam, reg_type):
    has_limits = bool(np.isfinite(lower).any() or np.isfinite(upper).any())
    ref = _backward_pass(
        _LQProblem.build(A, B, derivs, U, lower, upper, reg_type), lam, has_limits, ILQROptions()
    )
    ok, k, K, dV1, dV2 = kernels.backward_pass(
        A, B, *derivs, lower[None] - U, upper[None] - U, lam, reg_type, has_limits, PRM
    )
    return ref, (ok, k, K, dV1, dV2)


@pytest.mark.parametrize("reg_type", [1, 2])
@pytest.mark.parametrize("bounded", [True, False])
@pytest.mark.parametrize("n,m", [(4, 2), (3, 1), (6, 3)])
def test_kernel_matches_numpy_reference(reg_type, bounded, n, m):
    A, B, derivs, U = random_problem(60, n, m, seed=10 * n + m + reg_type)
    bound = 1.0 if bounded else np.inf
    lower, upper = np.full(m, -bound), np.full(m, bound)
    ref, (ok, k, K, dV1, dV2) = run_both(A, B, derivs, U, lower, upper, 0.3, reg_type)
    assert ref is not None and ok
    k_ref, K_ref, dV1_ref, dV2_ref = ref
    if bounded:  # the problem really exercises the box QP
        assert np.any(np.isclose(U + k, lower) | np.isclose(U + k, upper))
        assert np.all(U + k >= lower - 1e-12) and np.all(U + k <= upper + 1e-12)
    scale = 1.0 + np.abs(K_ref).max()
    np.testing.assert_allclose(k, k_ref, rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose(K, K_ref, rtol=0, atol=1e-10 * scale)
    np.testing.assert_allclose([dV1, dV2], [dV1_ref, dV2_ref], rtol=1e-10)


@pytest.mark.parametrize("reg_type", [1, 2])
@pytest.mark.parametrize("n,m,lux", [(70, 3, 1.0), (80, 60, 0.0)])
def test_kernel_matches_numpy_reference_with_a_large_state(reg_type, n, m, lux):
    """Products of 2^18 multiply-adds or more go through BLAS (n = 70: those of n x n; n = 80,
    m = 60: every product, B^T B and K^T Quu K included), the rest through the loops (at m = 60
    a random ``l_ux`` makes the stage Hessian indefinite: it is 0 there)."""
    A, B, derivs, U = random_problem(8, n, m, seed=7 + reg_type)
    derivs = (*derivs[:4], lux * derivs[4])
    lower, upper = np.full(m, -1.0), np.full(m, 1.0)
    ref, (ok, k, K, dV1, dV2) = run_both(A, B, derivs, U, lower, upper, 0.3, reg_type)
    assert ref is not None and ok
    scale = 1.0 + np.abs(ref[1]).max()
    np.testing.assert_allclose(k, ref[0], rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(K, ref[1], rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose([dV1, dV2], ref[2:], rtol=1e-9)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    lam=st.sampled_from([0.0, 1e-6, 0.1, 10.0]),
    reg_type=st.sampled_from([1, 2]),
    half_width=st.floats(0.0, 2.0),
)
def test_kernel_matches_reference_hypothesis(seed, lam, reg_type, half_width):
    """Random problems incl. zero-width boxes (fixed controls) and no regularisation."""
    A, B, derivs, _ = random_problem(15, 3, 2, seed)
    U = np.zeros((15, 2))
    lower, upper = np.full(2, -half_width), np.full(2, half_width)
    ref, (ok, k, K, dV1, dV2) = run_both(A, B, derivs, U, lower, upper, lam, reg_type)
    assert ok == (ref is not None)
    if ok:
        scale = 1.0 + np.abs(ref[1]).max() + np.abs(ref[0]).max()
        np.testing.assert_allclose(k, ref[0], rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(K, ref[1], rtol=0, atol=1e-9 * scale)
        assert np.all(k >= -half_width - 1e-12) and np.all(k <= half_width + 1e-12)


def test_not_positive_definite_is_reported():
    A, B, derivs, U = random_problem(10, 3, 2, seed=3)
    derivs[3][4] = -5.0 * np.eye(2)  # luu at t = 4 negative definite
    inf = np.full(2, np.inf)
    ref, (ok, *_rest) = run_both(A, B, derivs, U, -inf, inf, 0.0, 1)
    assert ref is None and not ok
    _, (ok_big_lam, *_rest) = run_both(A, B, derivs, U, -inf, inf, 1e3, 1)
    assert ok_big_lam


def test_first_iteration_is_the_exact_lq_solution():
    """lambda = 0, no limits: ``du_t = k_t + K_t dx_t`` solves the dense QP in ``du``."""
    T, n, m = 12, 3, 2
    A, B, (lx, lu, lxx, luu, lux), U = random_problem(T, n, m, seed=7)
    # dense: dx = S du with dx_0 = 0;  J(du) = 0.5 du^T H du + g^T du (+ const)
    S = np.zeros((T + 1, n, T, m))
    for t in range(T):
        S[t + 1] = np.einsum("ij,jsk->isk", A[t], S[t])
        S[t + 1, :, t] += B[t]
    S = S.reshape(T + 1, n, T * m)
    E = np.zeros((T, m, T * m))  # du_t = E_t du
    for t in range(T):
        E[t, :, t * m : (t + 1) * m] = np.eye(m)
    H = sum(S[t].T @ lxx[t] @ S[t] for t in range(T + 1))
    H = H + sum(E[t].T @ luu[t] @ E[t] + E[t].T @ lux[t] @ S[t] + S[t].T @ lux[t].T @ E[t]
                for t in range(T))
    g = sum(S[t].T @ lx[t] for t in range(T + 1)) + sum(E[t].T @ lu[t] for t in range(T))
    du_star = -np.linalg.solve(H, g)
    inf = np.full(m, np.inf)
    ok, k, K, dV1, dV2 = kernels.backward_pass(
        A, B, lx, lu, lxx, luu, lux, -inf[None] - U, inf[None] - U, 0.0, 1, False, PRM
    )
    assert ok
    dx = np.zeros(n)
    du = np.empty((T, m))
    for t in range(T):
        du[t] = k[t] + K[t] @ dx
        dx = A[t] @ dx + B[t] @ du[t]
    np.testing.assert_allclose(du.ravel(), du_star, rtol=0, atol=1e-9 * np.abs(du_star).max())
    # the expected change dV1 + dV2 is the exact change of the quadratic model
    np.testing.assert_allclose(dV1 + dV2, g @ du_star + 0.5 * du_star @ H @ du_star, rtol=1e-9)


@pytest.mark.parametrize("seed", range(8))
def test_box_qp_matches_scipy_bvls(seed):
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 7))
    G = rng.standard_normal((m, m))
    H = G @ G.T + 0.1 * np.eye(m)
    g = 3.0 * rng.standard_normal(m)
    lo = -rng.uniform(0.0, 1.0, m)
    hi = rng.uniform(0.0, 1.0, m)
    # 0.5 x^T H x + g^T x = 0.5 ||C^T x + C^-1 g||^2 + const with H = C C^T
    C = np.linalg.cholesky(H)
    ref = lsq_linear(C.T, -np.linalg.solve(C, g), bounds=(lo, hi), method="bvls", tol=1e-14)
    x, free, L, idx, b = (np.empty(m), np.empty(m, dtype=np.bool_), np.empty((m, m)),
                          np.empty(m, dtype=np.int64), np.empty(m))  # the kernel's buffers
    ok = kernels._box_qp(H, g, lo, hi, np.zeros(m), x, free, L, idx, b, PRM)
    assert ok
    np.testing.assert_allclose(x, ref.x, rtol=0, atol=1e-7)
    x_np, free_np, ok_np = _box_qp(H, g, lo, hi, np.zeros(m), ILQROptions())
    np.testing.assert_allclose(x, x_np, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(free, free_np)
    value = lambda z: 0.5 * z @ H @ z + g @ z  # noqa: E731
    assert value(x) <= value(ref.x) + 1e-12 * (1 + abs(value(ref.x)))


def test_compile_cache_is_used_by_a_fresh_process():
    """After the first compile, a new process loads the kernel from numba's cache (no compile).

    The first-ever compile takes ~7 s on a quiet 2-core machine (``scripts/bench_ilqr.py``
    measures it in a fresh process with an empty cache); CI pays it once per run.
    """
    A, B, derivs, U = random_problem(5, 2, 1, seed=0)
    kernels.backward_pass(A, B, *derivs, -1 - U, 1 - U, 0.1, 1, True, PRM)  # compile/cache
    code = (
        "import numpy as np; from mbtsr import _lqr_kernels as k; z = np.zeros;"
        "ok = k.backward_pass(z((3, 2, 2)) + np.eye(2), z((3, 2, 1)) + 1,"
        " z((4, 2)), z((3, 1)), z((4, 2, 2)) + np.eye(2), z((3, 1, 1)) + 1, z((3, 1, 2)),"
        " z((3, 1)) - 1, z((3, 1)) + 1, 0.1, 1, True, k.BOXQP_DEFAULTS)[0];"
        "s = k.backward_pass.stats; assert ok;"
        "print(sum(s.cache_hits.values()), sum(s.cache_misses.values()))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    hits, misses = (int(v) for v in out.stdout.split())
    assert hits == 1 and misses == 0, out.stdout


class _GenericLinear:
    """The same affine model as LinearDynamics, but not one (takes the generic rollout path)."""

    def __init__(self, lin: LinearDynamics) -> None:
        self.lin, self.state_dim, self.action_dim = lin, lin.state_dim, lin.action_dim

    def step(self, x, u, t=None):
        return self.lin.step(x, u, t)


@pytest.mark.parametrize("kill_some", [False, True])
def test_affine_rollout_kernel_matches_generic_rollout(kill_some):
    rng = np.random.default_rng(5)
    n, m, T = 4, 2, 30
    lin = LinearDynamics(np.eye(n) + 0.1 * rng.standard_normal((n, n)),
                         rng.standard_normal((n, m)), 0.01 * rng.standard_normal(n))
    x0 = rng.standard_normal(n)
    X = rng.standard_normal((T + 1, n))
    U = rng.uniform(-1, 1, (T, m))
    k = rng.standard_normal((T, m))
    K = 0.3 * rng.standard_normal((T, m, n))
    alphas = np.array(ILQROptions().alphas)
    lower, upper = np.array([-1.0, -np.inf]), np.array([0.5, np.inf])
    max_norm = 1e8
    if kill_some:  # a norm bound between the rows' peaks: some rows die, some live
        Xn, _, _ = _rollout_policy(lin, x0, X, U, k, K, alphas, lower, upper, 0, max_norm)
        max_norm = float(np.median(np.abs(Xn).max(axis=(1, 2))))
    fast = _rollout_policy(lin, x0, X, U, k, K, alphas, lower, upper, 0, max_norm)
    ref = _rollout_policy(_GenericLinear(lin), x0, X, U, k, K, alphas, lower, upper, 0, max_norm)
    for a, b in zip(fast, ref):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    if kill_some:
        assert 0 < ref[2].sum() < len(alphas)


class _Recording:
    """A nonlinear model (damped pendulum, 2 states, 1 input) recording its batch sizes."""

    state_dim, action_dim = 2, 1

    def __init__(self, chunked: bool) -> None:
        self.line_search_chunks = LINE_SEARCH_CHUNKS if chunked else None
        self.batches: list[int] = []

    def step(self, x, u, t=None):
        x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
        self.batches.append(x.reshape(-1, 2).shape[0])
        th, om = x[..., 0], x[..., 1]
        om_next = om + 0.05 * (-9.81 * np.sin(th) - 0.1 * om + 2.0 * u[..., 0])
        return np.stack([th + 0.05 * om_next, om_next], axis=-1)

    def jacobians(self, x, u, t=0):
        th = x[:, 0]
        T = x.shape[0]
        A = np.zeros((T, 2, 2))
        A[:, 1, 0] = -0.05 * 9.81 * np.cos(th)
        A[:, 1, 1] = 1 - 0.005
        A[:, 0, 0] = 1 + 0.05 * A[:, 1, 0]
        A[:, 0, 1] = 0.05 * A[:, 1, 1]
        B = np.zeros((T, 2, 1))
        B[:, 1, 0] = 0.1
        B[:, 0, 0] = 0.05 * 0.1
        return A, B


def test_chunked_line_search_accepts_the_same_steps():
    """``line_search_chunks`` models get the step sizes in chunks 2, 2, 3, rest; same iterates."""
    cost = quadratic_cost(np.diag([10.0, 0.1]), 0.01 * np.eye(1), np.array([2.5, 0.0]))
    T = 40
    runs = {}
    for flag in (False, True):
        model = _Recording(flag)
        runs[flag] = (ilqr(cost, model, np.zeros(2), np.zeros((T, 1)), u_min=-1, u_max=1), model)
    (a, _), (b, chunked) = runs[False], runs[True]
    np.testing.assert_array_equal(a.U, b.U)
    assert [tr["alpha"] for tr in a.trace] == [tr["alpha"] for tr in b.trace]
    sizes = set(chunked.batches[T:])  # after the initial rollout
    assert sizes <= {2, 3, 4} and 2 in sizes
    assert len(chunked.batches) < len(runs[False][1].batches) * 3  # not one call per step size
    assert sum(chunked.batches) < sum(runs[False][1].batches)  # fewer simulated steps

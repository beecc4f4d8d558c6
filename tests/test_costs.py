"""Tests of mbtsr.costs: values against direct numpy formulas, derivatives against finite
differences, time indexing, batching, and input validation."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from mbtsr.costs import CasadiCost, quadratic_cost, smooth_norm

N_X, N_U = 4, 2


def _random_psd(rng, k, rank=None):
    L = rng.standard_normal((k, rank or k))
    return L @ L.T


def _nonlinear_cost(params=None):
    """A cost exercising every derivative block: x-u coupling, t and p dependence."""
    x, u, t = ca.SX.sym("x", N_X), ca.SX.sym("u", N_U), ca.SX.sym("t")
    p = ca.SX.sym("p", 2) if params is not None else None
    target = p if p is not None else ca.DM([0.3, -0.2])
    stage = (
        smooth_norm(x[:2] - target, 0.1)
        + 0.5 * ca.sumsqr(u)
        + 0.3 * u[0] * ca.sin(x[1]) * x[2]
        + 0.01 * t * ca.sumsqr(x[2:])
        + ca.cos(u[1] * x[3])
    )
    terminal = 5.0 * ca.sumsqr(x[:2] - target) + ca.exp(0.1 * x[2])
    return CasadiCost.from_expressions(x, u, stage, terminal, t=t, p=p, params=params)


def _quadratic_reference(Q, R, Qf, xg, ur, X, U, t0):
    """Direct numpy evaluation of the quadratic tracking cost (last reference row held)."""
    T = U.shape[0]
    J = 0.0
    for k in range(T):
        g = xg[min(t0 + k, len(xg) - 1)]
        r = ur[min(t0 + k, len(ur) - 1)]
        J += (X[k] - g) @ Q @ (X[k] - g) + (U[k] - r) @ R @ (U[k] - r)
    g = xg[min(t0 + T, len(xg) - 1)]
    return J + (X[T] - g) @ Qf @ (X[T] - g)


@pytest.mark.parametrize("t0", [0, 3, 20])
def test_quadratic_cost_matches_numpy_formula_with_time_indexed_reference(t0):
    rng = np.random.default_rng(0)
    Q, R, Qf = _random_psd(rng, N_X, 2), _random_psd(rng, N_U), _random_psd(rng, N_X)
    xg, ur = rng.standard_normal((12, N_X)), rng.standard_normal((7, N_U))
    cost = quadratic_cost(Q, R, xg, u_ref=ur, Qf=Qf)
    X, U = rng.standard_normal((9, N_X)), rng.standard_normal((8, N_U))
    # the shorter reference is padded with its last row, as documented
    ur_padded = np.vstack([ur, np.repeat(ur[-1:], 5, axis=0)])
    want = _quadratic_reference(Q, R, Qf, xg, ur_padded, X, U, t0)
    assert cost.total(X, U, t0) == pytest.approx(want, rel=1e-12)


def test_quadratic_cost_defaults_terminal_weight_to_Q_and_zero_u_ref():
    rng = np.random.default_rng(1)
    Q, R = _random_psd(rng, N_X), _random_psd(rng, N_U)
    xg = rng.standard_normal(N_X)
    cost = quadratic_cost(Q, R, xg)
    X, U = rng.standard_normal((4, N_X)), rng.standard_normal((3, N_U))
    want = _quadratic_reference(Q, R, Q, xg[None], np.zeros((1, N_U)), X, U, 0)
    assert cost.total(X, U) == pytest.approx(want, rel=1e-12)


def test_quadratic_cost_derivatives_closed_form():
    rng = np.random.default_rng(2)
    Q, R, Qf = _random_psd(rng, N_X), _random_psd(rng, N_U), _random_psd(rng, N_X)
    xg = rng.standard_normal((6, N_X))
    cost = quadratic_cost(Q, R, xg, Qf=Qf)
    X, U = rng.standard_normal((6, N_X)), rng.standard_normal((5, N_U))
    d = cost.derivatives(X, U, t0=0)
    np.testing.assert_allclose(d.lx[:-1], 2 * (X[:-1] - xg[:5]) @ Q, atol=1e-12)
    np.testing.assert_allclose(d.lx[-1], 2 * Qf @ (X[-1] - xg[5]), atol=1e-12)
    np.testing.assert_allclose(d.lu, 2 * U @ R, atol=1e-12)
    np.testing.assert_allclose(d.lxx[:-1], np.broadcast_to(2 * Q, (5, N_X, N_X)), atol=1e-12)
    np.testing.assert_allclose(d.lxx[-1], 2 * Qf, atol=1e-12)
    np.testing.assert_allclose(d.luu, np.broadcast_to(2 * R, (5, N_U, N_U)), atol=1e-12)
    np.testing.assert_allclose(d.lux, 0.0, atol=1e-12)


def _fd_derivatives(cost, X, U, t0, h=1e-4):
    """Central finite differences of the stage/terminal values (independent of CasADi AD)."""
    T = U.shape[0]
    times = np.arange(t0, t0 + T)

    def stage(x, u, k):
        return cost.stage_values(x[None], u[None], int(times[k]))[0]

    def terminal(x):
        return cost.terminal_values(x, t0 + T)

    def grad(f, z):
        g = np.zeros_like(z)
        for i in range(z.size):
            e = np.zeros_like(z)
            e[i] = h
            g[i] = (f(z + e) - f(z - e)) / (2 * h)
        return g

    lx = np.zeros((T + 1, cost.n))
    lu = np.zeros((T, cost.m))
    lxx = np.zeros((T + 1, cost.n, cost.n))
    luu = np.zeros((T, cost.m, cost.m))
    lux = np.zeros((T, cost.m, cost.n))
    for k in range(T):
        x, u = X[k], U[k]
        lx[k] = grad(lambda z, u=u, k=k: stage(z, u, k), x)
        lu[k] = grad(lambda z, x=x, k=k: stage(x, z, k), u)
        for i in range(cost.n):
            e = np.zeros(cost.n)
            e[i] = h
            gp = grad(lambda z, xe=x + e, k=k: stage(xe, z, k), u)
            gm = grad(lambda z, xe=x - e, k=k: stage(xe, z, k), u)
            lux[k, :, i] = (gp - gm) / (2 * h)
            lxx[k, :, i] = (
                grad(lambda z, u=u, k=k: stage(z, u, k), x + e)
                - grad(lambda z, u=u, k=k: stage(z, u, k), x - e)
            ) / (2 * h)
        for j in range(cost.m):
            e = np.zeros(cost.m)
            e[j] = h
            luu[k, :, j] = (
                grad(lambda z, x=x, k=k: stage(x, z, k), u + e)
                - grad(lambda z, x=x, k=k: stage(x, z, k), u - e)
            ) / (2 * h)
    lx[T] = grad(terminal, X[T])
    for i in range(cost.n):
        e = np.zeros(cost.n)
        e[i] = h
        lxx[T, :, i] = (grad(terminal, X[T] + e) - grad(terminal, X[T] - e)) / (2 * h)
    return lx, lu, lxx, luu, lux


@pytest.mark.parametrize("with_params", [False, True])
def test_derivatives_match_finite_differences(with_params):
    rng = np.random.default_rng(3)
    params = rng.standard_normal((5, 2)) if with_params else None
    cost = _nonlinear_cost(params)
    X, U = rng.standard_normal((4, N_X)), rng.standard_normal((3, N_U))
    t0 = 3
    got = cost.derivatives(X, U, t0)
    want = _fd_derivatives(cost, X, U, t0)
    for name, g, w in zip(("lx", "lu", "lxx", "luu", "lux"), got, want):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-5, err_msg=name)


def test_jit_compiled_cost_gives_the_same_numbers(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # CasADi's default writes its C files into the working folder
    rng = np.random.default_rng(4)
    x, u = ca.SX.sym("x", N_X), ca.SX.sym("u", N_U)
    stage = smooth_norm(x[:2], 0.05) + ca.sumsqr(u) + u[0] * x[3]
    plain = CasadiCost.from_expressions(x, u, stage, ca.sumsqr(x))
    jitted = CasadiCost.from_expressions(x, u, stage, ca.sumsqr(x), jit=True)
    X, U = rng.standard_normal((11, N_X)), rng.standard_normal((10, N_U))
    for a, b in zip(plain.derivatives(X, U), jitted.derivatives(X, U)):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13)
    assert jitted.total(X, U) == pytest.approx(plain.total(X, U), rel=1e-13)
    assert list(tmp_path.iterdir()) == []  # the JIT's temporary files go to a private folder


def _jit_pair(jit):
    x, u = ca.SX.sym("x", N_X), ca.SX.sym("u", N_U)
    stage = smooth_norm(x[:2], 0.05) + ca.sumsqr(u) + u[0] * ca.sin(x[3])
    return [CasadiCost.from_expressions(x, u, stage, ca.sumsqr(x), jit=j) for j in (False, jit)]


def test_a_deferred_jit_compiles_at_its_call_and_keeps_every_bit():
    """``jit=3``: interpreted for two calls, compiled from the third; CasADi's C code gives the
    interpreter's bits (so a run's numbers do not depend on when, or whether, it compiled)."""
    rng = np.random.default_rng(7)
    plain, later = _jit_pair(3)
    for call in range(1, 5):
        X, U = rng.standard_normal((11, N_X)), rng.standard_normal((10, N_U))
        for a, b in zip(plain.derivatives(X, U), later.derivatives(X, U)):
            np.testing.assert_array_equal(a, b)
        Xb, Ub = rng.standard_normal((5, 11, N_X)), rng.standard_normal((5, 10, N_U))
        np.testing.assert_array_equal(plain.total(Xb, Ub), later.total(Xb, Ub))
        assert [m.compiled for m in later._maps["derivs"]] == [call >= 3] * 2
    again = _jit_pair(True)[1]  # the same functions: compiled once per process, shared
    again.derivatives(X, U)
    assert all(a.fn is b.fn for a, b in zip(again._maps["derivs"], later._maps["derivs"]))
    with pytest.raises(ValueError, match="jit"):
        _jit_pair(0)


def test_without_a_c_compiler_the_cost_stays_interpreted_with_a_warning(monkeypatch):
    import mbtsr.costs as costs

    def no_compiler(opt_level="-O2"):
        opts = costs.casadi_jit_options.__wrapped__(opt_level)
        opts["jit_options"]["compiler"] = "/nonexistent/cc"
        return opts

    no_compiler.__wrapped__ = costs.casadi_jit_options
    monkeypatch.setattr(costs, "casadi_jit_options", no_compiler)
    monkeypatch.setattr(costs, "_COMPILED", {})  # nothing compiled by the earlier tests
    rng = np.random.default_rng(8)
    X, U = rng.standard_normal((11, N_X)), rng.standard_normal((10, N_U))
    for jit in (True, 2):
        plain, jitted = _jit_pair(jit)
        with pytest.warns(RuntimeWarning, match="stays interpreted"):
            for _ in range(3):
                got = jitted.derivatives(X, U)
        for a, b in zip(plain.derivatives(X, U), got):
            np.testing.assert_array_equal(a, b)
        assert not any(m.compiled for m in jitted._maps["derivs"])


def test_batched_values_equal_per_trajectory_values():
    rng = np.random.default_rng(5)
    cost = _nonlinear_cost(rng.standard_normal((3, 2)))
    X, U = rng.standard_normal((3, 2, 7, N_X)), rng.standard_normal((3, 2, 6, N_U))
    batched = cost.total(X, U, t0=1)
    assert batched.shape == (3, 2)
    for i in range(3):
        for j in range(2):
            assert batched[i, j] == pytest.approx(cost.total(X[i, j], U[i, j], t0=1), rel=1e-13)
    stages = cost.stage_values(X[..., :-1, :], U, t0=1)
    assert stages.shape == (3, 2, 6)
    term = cost.terminal_values(X[..., -1, :], 7)
    np.testing.assert_allclose(stages.sum(-1) + term, batched, rtol=1e-13)


def test_shifted_horizon_sees_absolute_time():
    """The cost of the tail of a trajectory evaluated from t0 equals the tail of the stage sum."""
    rng = np.random.default_rng(6)
    cost = quadratic_cost(np.eye(N_X), np.eye(N_U), rng.standard_normal((30, N_X)))
    X, U = rng.standard_normal((21, N_X)), rng.standard_normal((20, N_U))
    full = cost.stage_values(X[:-1], U, t0=0)
    tail = cost.stage_values(X[5:-1], U[5:], t0=5)
    np.testing.assert_allclose(tail, full[5:], rtol=1e-13)


def test_cost_from_mx_function_works():
    x, u, t = ca.MX.sym("x", N_X), ca.MX.sym("u", N_U), ca.MX.sym("t")
    stage = ca.Function("s", [x, u, t], [ca.sumsqr(x) + 2 * ca.sumsqr(u)])
    terminal = ca.Function("f", [x], [3 * ca.sumsqr(x)])
    cost = CasadiCost(stage, terminal, N_X, N_U)
    X, U = np.ones((3, N_X)), np.ones((2, N_U))
    assert cost.total(X, U) == pytest.approx(2 * (4 + 4) + 12)
    np.testing.assert_allclose(cost.derivatives(X, U).lu, 4 * U)


@settings(max_examples=50, deadline=None)
@given(
    v=arrays(np.float64, st.integers(1, 5), elements=st.floats(-1e3, 1e3)),
    eps=st.floats(1e-4, 10.0),
)
def test_smooth_norm_bounds_and_symbolic_agreement(v, eps):
    s = smooth_norm(v, eps)
    norm = np.linalg.norm(v)
    assert s >= -1e-12
    assert norm - eps - 1e-9 <= s <= norm + 1e-9
    sym = smooth_norm(ca.DM(v), eps)
    assert float(sym) == pytest.approx(s, rel=1e-9, abs=1e-12)


def test_smooth_norm_is_zero_at_zero_and_smooth():
    x = ca.SX.sym("x", 3)
    g = ca.Function("g", [x], [ca.gradient(smooth_norm(x, 0.1), x)])
    assert smooth_norm(np.zeros(3), 0.1) == 0.0
    np.testing.assert_allclose(np.asarray(g(np.zeros(3))).ravel(), 0.0)


# ---------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"Q": np.ones((4, 3))}, "Q must be a square"),
        ({"Q": np.triu(np.ones((4, 4)))}, "Q must be symmetric"),
        ({"Q": -np.eye(4)}, "Q must be positive semi-definite"),
        ({"R": np.full((2, 2), np.nan)}, "R contains"),
        ({"x_goal": np.zeros(3)}, "x_goal must be"),
        ({"x_goal": np.zeros((5, 3))}, "x_goal must be"),
        ({"u_ref": np.zeros(3)}, "u_ref must be"),
        ({"Qf": np.eye(3)}, "Qf must have shape"),
    ],
)
def test_quadratic_cost_rejects_bad_input(kwargs, match):
    args = {"Q": np.eye(4), "R": np.eye(2), "x_goal": np.zeros(4)} | kwargs
    with pytest.raises(ValueError, match=match):
        quadratic_cost(**args)


def test_casadi_cost_rejects_wrong_function_shapes():
    x, u, t = ca.SX.sym("x", 3), ca.SX.sym("u", 2), ca.SX.sym("t")
    stage = ca.Function("s", [x, u, t], [ca.sumsqr(x)])
    terminal = ca.Function("f", [x], [ca.sumsqr(x)])
    with pytest.raises(ValueError, match="stage input 0 must have shape"):
        CasadiCost(stage, terminal, 4, 2)
    x4 = ca.SX.sym("x", 4)
    vec_out = ca.Function("s", [x4, u, t], [x4])
    with pytest.raises(ValueError, match="scalar"):
        CasadiCost(vec_out, ca.Function("f", [ca.SX.sym("y", 4)], [0]), 4, 2)
    with pytest.raises(TypeError, match="casadi.Function"):
        CasadiCost(lambda x: x, terminal, 3, 2)
    with pytest.raises(ValueError, match="params given"):
        CasadiCost(stage, terminal, 3, 2, params=np.zeros((2, 1)))


def test_cost_evaluation_rejects_bad_arrays():
    cost = quadratic_cost(np.eye(4), np.eye(2), np.zeros(4))
    X, U = np.zeros((4, 4)), np.zeros((3, 2))
    with pytest.raises(ValueError, match=r"X must be \[\.\.\., T\+1, n\]"):
        cost.total(X[:-1], U)
    with pytest.raises(ValueError, match="U must be"):
        cost.total(X, np.zeros((3, 3)))
    X_nan = X.copy()
    X_nan[2, 1] = np.nan
    with pytest.raises(ValueError, match="X contains 1 non-finite"):
        cost.derivatives(X_nan, U)
    with pytest.raises(ValueError, match="t0 must be an integer"):
        cost.total(X, U, t0=-1)
    with pytest.raises(ValueError, match="eps must be"):
        smooth_norm(np.ones(2), 0.0)


# ---------------------------------------------------------------------- parameters at call time
def test_params_at_call_time_equal_a_cost_built_with_them_as_defaults():
    """One compiled cost, any target: call-time params give the numbers of a cost whose
    defaults are those params, for values, derivatives and the symbolic view."""
    rng = np.random.default_rng(11)
    Q, R = _random_psd(rng, N_X), _random_psd(rng, N_U)
    one = quadratic_cost(Q, R)  # default goal 0
    X, U = rng.standard_normal((2, 6, N_X)), rng.standard_normal((2, 5, N_U))
    for _ in range(3):
        goal = rng.standard_normal(N_X)
        own = quadratic_cost(Q, R, goal)
        p = one.reference(goal)
        np.testing.assert_allclose(one.total(X, U, 2, p), own.total(X, U, 2), rtol=1e-13)
        for a, b in zip(one.derivatives(X[0], U[0], 1, p), own.derivatives(X[0], U[0], 1)):
            np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13)
        want = (X[0, :-1] - goal) @ Q
        np.testing.assert_allclose(one.derivatives(X[0], U[0], 0, p).lx[:-1], 2 * want)
    assert sorted(one._maps) == ["derivs", "values"]  # no new CasADi function per target


def test_vector_params_equal_a_one_row_table_and_a_table_is_indexed_by_absolute_time():
    rng = np.random.default_rng(12)
    cost = _nonlinear_cost(rng.standard_normal((1, 2)))
    X, U = rng.standard_normal((6, N_X)), rng.standard_normal((5, N_U))
    p = rng.standard_normal(2)
    assert cost.total(X, U, 0, p) == cost.total(X, U, 0, p[None])
    table = rng.standard_normal((4, 2))
    # stage values at t0=2 use rows 2, 3, 3, 3, 3 (last row held)
    got = cost.stage_values(X[:-1], U, 2, table)
    want = [cost.stage_values(X[k:k + 1], U[k:k + 1], 2 + k, table[min(2 + k, 3)])[0]
            for k in range(5)]
    np.testing.assert_allclose(got, want, rtol=1e-14)


@pytest.mark.parametrize(
    "params, match",
    [
        (np.zeros(3), r"params must be \[2\] or \[N_ref, 2\]"),
        (np.zeros((0, 2)), "N_ref >= 1"),
        (np.zeros((2, 2, 1)), "params must be"),
        (np.array([0.0, np.inf]), "params contains 1 non-finite"),
        ("abc", "params must be numeric"),
    ],
)
def test_bad_params_are_named(params, match):
    cost = _nonlinear_cost(np.zeros((1, 2)))
    X, U = np.zeros((3, N_X)), np.zeros((2, N_U))
    for call in (lambda: cost.total(X, U, 0, params), lambda: cost.derivatives(X, U, 0, params)):
        with pytest.raises(ValueError, match=match):
            call()


def test_params_required_without_defaults_and_refused_without_a_parameter_input():
    x, u, p = ca.SX.sym("x", 2), ca.SX.sym("u", 1), ca.SX.sym("p", 2)
    cost = CasadiCost.from_expressions(x, u, ca.sumsqr(x - p), ca.sumsqr(x), p=p)
    X, U = np.ones((3, 2)), np.ones((2, 1))
    with pytest.raises(ValueError, match="params is required"):
        cost.total(X, U)
    assert cost.total(X, U, 0, np.ones(2)) == 0.0 + 2.0  # stages 0, terminal |x|^2 = 2
    plain = CasadiCost.from_expressions(x, u, ca.sumsqr(x), ca.sumsqr(x))
    with pytest.raises(ValueError, match="takes no parameters"):
        plain.total(X, U, 0, np.ones(2))


@pytest.mark.parametrize("constant", ["terminal", "stage_x", "stage_u"])
def test_costs_independent_of_x_or_u_have_zero_not_uninitialised_derivatives(constant):
    """A terminal cost constant in x (or a stage cost without x or u) has structurally zero
    derivatives; they must come back as zeros (finite differences), not as np.empty memory."""
    x, u = ca.SX.sym("x", 3), ca.SX.sym("u", 2)
    stage = {"terminal": ca.sumsqr(x) + ca.sumsqr(u) * x[0], "stage_x": ca.sumsqr(u),
             "stage_u": ca.sin(x[0]) * x[1]}[constant]
    terminal = ca.DM(3.0) if constant == "terminal" else ca.sumsqr(x)
    rng = np.random.default_rng(13)
    X, U = rng.standard_normal((5, 3)), rng.standard_normal((4, 2))
    cost = CasadiCost.from_expressions(x, u, stage, terminal)
    want = _fd_derivatives(cost, X, U, 0)
    shapes = [(4, 3), (4, 2), (4, 3, 3), (4, 2, 2), (4, 2, 3), (3,), (3, 3)]
    for _ in range(5):
        junk = [np.full(s, 7.0) for s in shapes]  # freed memory that np.empty would hand back
        del junk
        got = cost.derivatives(X, U)
        for name, g, w in zip(("lx", "lu", "lxx", "luu", "lux"), got, want):
            np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6, err_msg=name)
            # a constant's central difference is exactly 0: so must the derivative be
            np.testing.assert_array_equal(g[w == 0.0], 0.0, err_msg=name)


def _stage_hessians(d):
    T, m, n = d.lux.shape
    H = np.zeros((T, n + m, n + m))
    H[:, :n, :n], H[:, n:, n:], H[:, n:, :n] = d.lxx[:T], d.luu, d.lux
    H[:, :n, n:] = np.swapaxes(d.lux, 1, 2)
    return H


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 4), st.integers(1, 3), st.integers(1, 5),
       st.booleans())
def test_convexified_hessians_are_the_nearest_psd_matrices(seed, n, m, T, constant):
    from scipy.linalg import polar

    from mbtsr.costs import CostDerivatives

    rng = np.random.default_rng(seed)
    G = rng.standard_normal((T + 1, n + m, n + m))
    if constant:  # a quadratic cost's Hessian: one matrix at every stage (a separate path)
        G[:T] = G[0]
    H = G + np.swapaxes(G, 1, 2)
    H[T, n:, :], H[T, :, n:] = 0.0, 0.0  # the terminal stage has only lxx
    d = CostDerivatives(lx=rng.standard_normal((T + 1, n)), lu=rng.standard_normal((T, m)),
                        lxx=H[:, :n, :n].copy(), luu=H[:T, n:, n:].copy(),
                        lux=H[:T, n:, :n].copy())
    c = d.convexified()
    assert c.lx is d.lx and c.lu is d.lu  # gradients untouched
    got = np.concatenate([_stage_hessians(c), np.pad(c.lxx[T:], ((0, 0), (0, m), (0, m)))])
    for k in range(T + 1):
        # Higham: the nearest symmetric PSD matrix to a symmetric H is (H + P) / 2 with P the
        # symmetric polar factor of H (an independent formula from the eigenvalue clipping)
        Hk = H[k] if k < T else np.pad(H[k, :n, :n], ((0, m), (0, m)))
        want = 0.5 * (Hk + polar(Hk)[1])
        np.testing.assert_allclose(got[k], want, atol=1e-9)
        assert np.linalg.eigvalsh(got[k]).min() >= -1e-9


def test_convexified_leaves_psd_stages_bit_for_bit():
    from mbtsr.costs import CostDerivatives

    rng = np.random.default_rng(0)
    n, m, T = 3, 2, 4
    G = rng.standard_normal((T + 1, n + m, n + m))
    H = G @ np.swapaxes(G, 1, 2)  # PSD
    H[1, 0, 0] = -5.0  # ... but stage 1
    d = CostDerivatives(lx=np.zeros((T + 1, n)), lu=np.zeros((T, m)), lxx=H[:, :n, :n].copy(),
                        luu=H[:T, n:, n:].copy(), lux=H[:T, n:, :n].copy())
    c = d.convexified()
    for k in (0, 2, 3):
        np.testing.assert_array_equal(_stage_hessians(c)[k], _stage_hessians(d)[k])
    assert np.linalg.eigvalsh(_stage_hessians(c)[1]).min() >= -1e-12
    assert not np.array_equal(_stage_hessians(c)[1], _stage_hessians(d)[1])
    psd = CostDerivatives(lx=d.lx, lu=d.lu, lxx=np.array([np.eye(n)] * (T + 1)),
                          luu=np.array([np.eye(m)] * T), lux=np.zeros((T, m, n)))
    assert psd.convexified() is psd

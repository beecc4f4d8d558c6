"""Tests of mbtsr.cem against independent solutions: the finite-horizon Riccati optimum of a
linear-quadratic problem, box constraints, seeding, termination masking, and the shared
optimizer interface (same result fields as iLQR)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbtsr.cem import CEMOptions, cem
from mbtsr.costs import quadratic_cost
from mbtsr.dynamics import LinearDynamics, rollout
from mbtsr.ilqr import ilqr

DT = 0.1
A = np.array([[1.0, DT], [0.0, 1.0]])
B = np.array([[0.5 * DT**2], [DT]])
Q = np.diag([1.0, 0.1])
R = np.array([[0.01]])
Qf = np.diag([10.0, 1.0])
X0 = np.array([1.0, 0.0])


def riccati_cost(T: int) -> float:
    """Optimal cost x0^T P_0 x0 of sum_t x^T Q x + u^T R u + x_T^T Qf x_T (no bounds)."""
    P = Qf
    for _ in range(T):
        K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        P = Q + A.T @ P @ (A - B @ K)
    return float(X0 @ P @ X0)


def problem(T: int = 10):
    return quadratic_cost(Q, R, np.zeros(2), Qf=Qf), LinearDynamics(A, B), np.zeros((T, 1))


def test_cem_reaches_the_riccati_optimum_of_a_linear_quadratic_problem():
    cost, model, U0 = problem(10)
    res = cem(cost, model, X0, U0, u_min=-50.0, u_max=50.0,
              options=CEMOptions(samples=400, elites=40, iterations=40, init_std=0.2))
    optimum = riccati_cost(10)
    assert res.cost >= optimum * (1 - 1e-12)  # nothing beats the optimum
    assert res.cost <= 1.01 * optimum, (res.cost, optimum)
    # the reported cost and states are those of the returned controls
    assert res.cost == pytest.approx(cost.total(res.X, res.U), rel=1e-12)
    np.testing.assert_allclose(res.X[1:], np.stack(
        [A @ x + B @ u for x, u in zip(res.X[:-1], res.U)]), atol=1e-12)
    assert res.status in ("converged", "max_iter") and res.iterations >= 1
    # the best cost never increases over iterations
    best = [r["best_cost"] for r in res.trace]
    assert all(b2 <= b1 for b1, b2 in zip(best, best[1:]))


def test_cem_agrees_with_ilqr_on_a_bounded_problem():
    """With tight bounds both optimisers should find the same constrained optimum."""
    cost, model, U0 = problem(10)
    ref = ilqr(cost, model, X0, U0, u_min=-2.0, u_max=2.0)
    res = cem(cost, model, X0, U0, u_min=-2.0, u_max=2.0,
              options={"samples": 400, "elites": 40, "iterations": 40, "init_std": 0.3})
    assert np.all(res.U >= -2.0) and np.all(res.U <= 2.0)
    assert res.cost <= 1.01 * ref.cost


@settings(max_examples=15, deadline=None)
@given(lo=st.floats(-3.0, 0.5), width=st.floats(0.01, 4.0), seed=st.integers(0, 2**31 - 1))
def test_cem_respects_asymmetric_bounds_and_is_seeded(lo, width, seed):
    cost, model, _ = problem(6)
    U0 = np.full((6, 1), 10.0)  # outside the box: clipped
    opts = CEMOptions(samples=20, elites=4, iterations=3, seed=seed)
    res = cem(cost, model, X0, U0, u_min=lo, u_max=lo + width, options=opts)
    assert np.all(np.isfinite(res.U)) and np.all(np.isfinite(res.X))
    assert np.all(res.U >= lo) and np.all(res.U <= lo + width)
    again = cem(cost, model, X0, U0, u_min=lo, u_max=lo + width, options=opts)
    np.testing.assert_array_equal(again.U, res.U)
    assert again.cost == res.cost


def test_different_seeds_sample_differently():
    cost, model, U0 = problem(6)
    a = cem(cost, model, X0, U0, u_min=-5, u_max=5, options={"iterations": 1, "seed": 1})
    b = cem(cost, model, X0, U0, u_min=-5, u_max=5, options={"iterations": 1, "seed": 2})
    assert not np.array_equal(a.U, b.U)


def test_termination_drops_the_costs_after_the_predicted_end():
    """x stays at 1 (A = I, B = 0); with every x_t, t >= 1 terminal only stage 0 counts."""
    cost = quadratic_cost(np.eye(1), np.zeros((1, 1)), np.zeros(1), Qf=np.eye(1))
    model = LinearDynamics(np.eye(1), np.zeros((1, 1)))
    U0 = np.zeros((5, 1))
    full = cem(cost, model, np.ones(1), U0, u_min=-1, u_max=1, options={"iterations": 1})
    assert full.cost == pytest.approx(6.0)  # 5 stages + terminal
    ended = cem(cost, model, np.ones(1), U0, u_min=-1, u_max=1,
                options={"iterations": 1, "termination_cost": 0.5},
                terminated=lambda X: np.ones(X.shape[:-1], dtype=bool))
    assert ended.cost == pytest.approx(1.0 + 0.5)
    never = cem(cost, model, np.ones(1), U0, u_min=-1, u_max=1, options={"iterations": 1},
                terminated=lambda X: np.zeros(X.shape[:-1], dtype=bool))
    assert never.cost == pytest.approx(6.0)


def test_diverging_model_gives_failed_status_with_finite_controls():
    cost, _, U0 = problem(5)
    model = LinearDynamics(np.eye(2) * 1e9, B)
    res = cem(cost, model, X0, U0, u_min=-1, u_max=1, options={"iterations": 2})
    assert res.status == "failed" and res.cost == np.inf
    assert np.all(np.isfinite(res.U)) and np.all(np.abs(res.U) <= 1)
    assert np.all(np.isfinite(res.X))  # the diverged rollout holds its last finite state
    np.testing.assert_array_equal(res.X[0], X0)


@pytest.mark.parametrize("bad, match", [
    ({"samples": 1}, "samples"), ({"elites": 300}, "elites"), ({"smoothing": 2.0}, "smoothing"),
    ({"seed": -1}, "seed"), ({"nope": 1}, "unknown CEMOptions field"),
])
def test_bad_options_are_named(bad, match):
    cost, model, U0 = problem(3)
    with pytest.raises(ValueError, match=match):
        cem(cost, model, X0, U0, u_min=-1, u_max=1, options=bad)


def test_bad_inputs_are_named():
    cost, model, U0 = problem(3)
    with pytest.raises(ValueError, match="finite u_min"):
        cem(cost, model, X0, U0, u_min=-np.inf, u_max=1)
    with pytest.raises(ValueError, match="u_max must be > u_min"):
        cem(cost, model, X0, U0, u_min=1, u_max=1)
    with pytest.raises(ValueError, match="x0"):
        cem(cost, model, np.array([np.nan, 0.0]), U0, u_min=-1, u_max=1)


class TwoSystems:
    """A trajectory-sampling-like model: row ``r`` of a batch follows system ``r mod 2``."""

    state_dim, action_dim = 2, 1

    def __init__(self, A2, B2):
        self.A2, self.B2 = A2, B2

    def step(self, x, u, t=None):
        x, u = np.atleast_2d(x), np.atleast_2d(u)
        r = np.arange(len(x)) % 2
        return np.einsum("rij,rj->ri", self.A2[r], x) + np.einsum("rij,rj->ri", self.B2[r], u)

    def jacobians(self, x, u, t=0):  # pragma: no cover - CEM never asks
        raise TypeError


def test_particles_average_the_cost_over_the_rows_of_a_sequence():
    """With two particles per sequence on a model whose even rows follow system a and odd rows
    system b, CEM minimizes the mean of the two costs: the Riccati optimum of the stacked system
    ``[x_a; x_b]`` driven by the one control (state costs halved). One particle cannot: each
    sequence is scored on one system only."""
    A2 = np.stack([A, np.array([[1.0, DT], [-0.5 * DT, 1.0]])])
    B2 = np.stack([B, 2.0 * B])
    model = TwoSystems(A2, B2)
    T = 10
    cost = quadratic_cost(Q, R, np.zeros(2), Qf=Qf)
    Aa = np.block([[A2[0], np.zeros((2, 2))], [np.zeros((2, 2)), A2[1]]])
    Ba = np.concatenate([B2[0], B2[1]])
    Qa, Qfa = 0.5 * np.kron(np.eye(2), Q), 0.5 * np.kron(np.eye(2), Qf)
    P = Qfa
    for _ in range(T):
        K = np.linalg.solve(R + Ba.T @ P @ Ba, Ba.T @ P @ Aa)
        P = Qa + Aa.T @ P @ (Aa - Ba @ K)
    xa = np.concatenate([X0, X0])
    optimum = float(xa @ P @ xa)
    opts = dict(samples=400, elites=40, iterations=40, init_std=0.2)
    res = cem(cost, model, X0, np.zeros((T, 1)), u_min=-50.0, u_max=50.0,
              options=CEMOptions(particles=2, **opts))
    def mean_cost(U):  # the mean cost of U over the two systems
        total = 0.0
        for Ai, Bi in zip(A2, B2):
            X = [X0]
            for u in U:
                X.append(Ai @ X[-1] + Bi @ u)
            total += 0.5 * cost.total(np.array(X), U)
        return total

    assert res.cost == pytest.approx(mean_cost(res.U), rel=1e-10)
    assert optimum * (1 - 1e-12) <= res.cost <= 1.01 * optimum
    one = cem(cost, model, X0, np.zeros((T, 1)), u_min=-50.0, u_max=50.0,
              options=CEMOptions(particles=1, **opts))
    assert mean_cost(one.U) > 1.01 * optimum
    with pytest.raises(ValueError, match="options.particles must be an integer >= 1"):
        CEMOptions(particles=0)


class ControlDisagreement(LinearDynamics):
    """The linear test system with a 'disagreement' ``d(x, u) = 1 + u`` (first control), so
    that ``D(U) = T + sum_t u_t``: the scored objective ``J(U) - c D(U)`` is quadratic with a
    linear term, its minimizer closed form."""

    def disagreement(self, x, u):
        return 1.0 + np.asarray(u)[..., 0]


def lq_matrices(T: int) -> tuple[np.ndarray, np.ndarray]:
    """``(H, g)`` with ``J(U) = U^T H U + 2 g^T U + const`` for the module's LQ problem."""
    n = A.shape[0]
    Phi = [np.linalg.matrix_power(A, t) for t in range(T + 1)]
    Gam = np.zeros((T + 1, n, T))
    for t in range(1, T + 1):
        for s in range(t):
            Gam[t, :, s] = (Phi[t - 1 - s] @ B)[:, 0]
    H, g = R[0, 0] * np.eye(T), np.zeros(T)
    for t in range(T + 1):
        W = Qf if t == T else Q
        H += Gam[t].T @ W @ Gam[t]
        g += Gam[t].T @ W @ Phi[t] @ X0
    return H, g


def test_explore_weight_minimizes_cost_minus_scaled_disagreement():
    """With ``explore_weight`` CEM minimizes ``J(U) - c D(U)`` (``c`` from its trace): it lands
    on that closed-form minimizer, ``cost`` is the task cost ``J`` of the returned plan, its
    ``disagreement`` is ``D``; a larger weight buys more disagreement at more cost; weight 0
    is the plain solver exactly; a model without ``disagreement`` is refused."""
    T = 10
    cost, _, U0 = problem(T)
    model = ControlDisagreement(A, B)
    opts = dict(samples=400, elites=40, iterations=60, init_std=0.2)
    box = dict(u_min=-200.0, u_max=200.0)  # the scored minimizer is inside
    plain = cem(cost, model, X0, U0, **box, options=CEMOptions(**opts))
    same = cem(cost, model, X0, U0, **box,
               options=CEMOptions(explore_weight=0.0, **opts))
    np.testing.assert_array_equal(same.U, plain.U)
    assert plain.disagreement is None and "explore_scale" not in plain.trace[0]
    H, g = lq_matrices(T)
    # c by hand: the first iteration's samples (the solver's own draw), c = w std(J) / std(D)
    eps = np.random.default_rng(0).standard_normal((400, T, 1))
    cand = np.clip(U0[None] + 0.2 * 200.0 * eps, -200.0, 200.0)
    cand[0] = U0
    J1 = np.array([cost.total(rollout(model, X0, c), c) for c in cand])
    D1 = T + cand[:, :, 0].sum(1)
    scales = {}
    results = []
    for w in (0.1, 0.4):
        res = cem(cost, model, X0, U0, **box, options=CEMOptions(explore_weight=w, **opts))
        c = res.trace[0]["explore_scale"]
        assert c > 0 and all(r["explore_scale"] == c for r in res.trace)
        assert c == pytest.approx(w * np.std(J1) / np.std(D1), rel=1e-9)
        scales[w] = c
        best = np.linalg.solve(H, 0.5 * c * np.ones(T) - g)
        assert np.all(np.abs(best) < 200.0)
        def score(U, c=c):  # J(U) - c D(U) up to a constant
            u = U[:, 0]
            return u @ H @ u + 2 * g @ u - c * (T + u.sum())

        gap = score(res.U) - score(best[:, None])
        assert 0 <= gap <= 0.01 * (score(plain.U) - score(best[:, None]))  # 99 % of the way
        assert res.cost == pytest.approx(cost.total(res.X, res.U), rel=1e-12)
        assert res.disagreement == pytest.approx(T + res.U.sum(), rel=1e-12)
        results.append(res)
    assert scales[0.4] == pytest.approx(4 * scales[0.1], rel=1e-12)
    assert plain.cost < results[0].cost < results[1].cost
    assert T + plain.U.sum() < results[0].disagreement < results[1].disagreement
    with pytest.raises(ValueError, match=r"needs a model\s+with disagreement"):
        cem(cost, LinearDynamics(A, B), X0, U0, u_min=-5.0, u_max=5.0,
            options=CEMOptions(explore_weight=1.0))
    with pytest.raises(ValueError, match="options.explore_weight"):
        CEMOptions(explore_weight=-1.0)


class TwoMembers:
    """Two 'members' of a 3-state system ``[pos, vel, z]``: the double integrator, and ``z``
    (or ``pos``, with ``on_pos``) moved by ``+-0.5 u`` (member 0: -, member 1: +); the mean
    model is the double integrator with ``z`` constant."""

    state_dim, action_dim = 3, 1

    def __init__(self, on_pos: bool = False):
        self.dim = 0 if on_pos else 2

    def member_predictions(self, x, u):
        x, u = np.asarray(x, float), np.asarray(u, float)
        mean = np.concatenate([x[..., :2] @ A.T + u @ B.T, x[..., 2:]], -1)
        out = np.stack([mean, mean])
        out[0, ..., self.dim] -= 0.5 * u[..., 0]
        out[1, ..., self.dim] += 0.5 * u[..., 0]
        return out

    def step(self, x, u, t=None):
        return self.member_predictions(x, u).mean(0)

    def disagreement(self, x, u):
        return self.member_predictions(x, u).var(0).mean(-1)


def test_explore_on_cost_counts_only_the_disagreement_the_cost_sees():
    """``explore_on="cost"``: members that disagree only on a coordinate the cost ignores give
    no bonus (the plan is the plain one, bit for bit), where ``"state"`` explores; members that
    disagree on a costed coordinate give ``D`` = the members' std of the stage cost of their
    next states, summed (computed here from ``member_predictions`` and ``stage_values``)."""
    T = 8
    cost = quadratic_cost(np.diag([1.0, 0.1, 0.0]), R, np.zeros(3), Qf=np.diag([10.0, 1.0, 0.0]))
    x0, U0 = np.array([1.0, 0.0, 0.0]), np.zeros((T, 1))
    opts = dict(samples=100, elites=10, iterations=5, init_std=0.2)
    box = dict(u_min=-20.0, u_max=20.0)
    plain = cem(cost, TwoMembers(), x0, U0, **box, options=CEMOptions(**opts))
    on_cost = cem(cost, TwoMembers(), x0, U0, **box,
                  options=CEMOptions(explore_weight=1.0, explore_on="cost", **opts))
    np.testing.assert_array_equal(on_cost.U, plain.U)
    assert on_cost.disagreement == 0.0 and on_cost.trace[-1]["explore_scale"] is None
    on_state = cem(cost, TwoMembers(), x0, U0, **box,
                   options=CEMOptions(explore_weight=1.0, explore_on="state", **opts))
    assert on_state.trace[0]["explore_scale"] > 0 and not np.allclose(on_state.U, plain.U)
    model = TwoMembers(on_pos=True)
    res = cem(cost, model, x0, U0, **box,
              options=CEMOptions(explore_weight=1.0, explore_on="cost", **opts))
    assert res.trace[0]["explore_scale"] > 0
    P = model.member_predictions(res.X[:-1], res.U)
    want = sum(np.std([cost.stage_values(P[k, t][None], res.U[t][None], t + 1)[0]
                       for k in range(2)]) for t in range(T))
    assert res.disagreement == pytest.approx(want, rel=1e-12)
    assert res.cost == pytest.approx(cost.total(res.X, res.U), rel=1e-12)
    with pytest.raises(ValueError, match=r"options.explore_on must be one of \('state', 'cost'\)"):
        CEMOptions(explore_on="value")


class TimedCost:
    """A stage cost ``p t x_0^2`` that depends on the absolute time and on ``params`` (a
    scalar ``p``), no terminal cost: checks which ``t`` and ``params`` the cost variant uses."""

    def stage_values(self, X, U, t0, params):
        T = X.shape[-2]
        return params * (t0 + np.arange(T)) * X[..., 0] ** 2

    def terminal_values(self, X, t, params):
        return np.zeros(X.shape[:-1])

    def total(self, X, U, t0, params):
        return self.stage_values(X[..., :-1, :], U, t0, params).sum(-1)


def test_explore_on_cost_scores_next_states_at_their_time_with_the_params():
    """The cost variant's ``d`` at step ``t`` is the members' std of ``l(x^k_{t+1}, u_t,
    t0 + t + 1, params)``: computed here with the solve's ``t0 = 3`` and ``params = 2``."""
    T, t0, p = 6, 3, 2.0
    model = TwoMembers(on_pos=True)
    res = cem(TimedCost(), model, np.array([1.0, 0.0, 0.0]), np.zeros((T, 1)), u_min=-5.0,
              u_max=5.0, params=p, t0=t0,
              options=CEMOptions(samples=50, elites=5, iterations=3, explore_weight=1.0,
                                 explore_on="cost"))
    P = model.member_predictions(res.X[:-1], res.U)  # [2, T, 3]
    want = sum(np.std(p * (t0 + t + 1) * P[:, t, 0] ** 2) for t in range(T))
    assert res.disagreement == pytest.approx(want, rel=1e-12)
    assert res.timings["disagreement"] > 0


class DisagreePastOne(LinearDynamics):
    """1-D integrator whose members disagree only beyond ``x > 1``, where the episode ends."""

    def disagreement(self, x, u):
        return (np.asarray(x)[..., 0] > 1.0).astype(float)


def test_disagreement_after_a_predicted_termination_does_not_count():
    """With ``terminated``, the bonus stops where the stage costs stop: members that disagree
    only past a termination (cost 5) do not lure the plan across it; a plan that crosses is
    credited only the steps before the end."""
    model, x0 = DisagreePastOne(np.eye(1), np.eye(1)), np.array([0.5])
    cost = quadratic_cost(np.eye(1), 0.01 * np.eye(1), np.zeros(1))
    ends = lambda X: X[..., 0] > 1.0  # noqa: E731
    opts = dict(samples=200, elites=20, iterations=20, termination_cost=5.0)
    plain = cem(cost, model, x0, np.zeros((10, 1)), u_min=-1, u_max=1, terminated=ends,
                options=CEMOptions(**opts))
    res = cem(cost, model, x0, np.zeros((10, 1)), u_min=-1, u_max=1, terminated=ends,
              options=CEMOptions(explore_weight=1.0, **opts))
    assert not np.any(res.X[1:, 0] > 1.0) and res.disagreement == 0.0
    assert res.cost == pytest.approx(plain.cost, rel=1e-9)
    # a plan that crosses at step 1 (x_2 > 1) and stays beyond: d(x_t) counts for t <= 1 only
    U = np.full((10, 1), 0.4)
    crossing = cem(cost, model, x0, U, u_min=-1, u_max=1, terminated=ends,
                   options=CEMOptions(samples=2, elites=1, iterations=1, init_std=0.0,
                                      explore_weight=1.0, termination_cost=5.0))
    np.testing.assert_allclose(crossing.U, U)
    assert crossing.X[2, 0] > 1.0 and crossing.disagreement == 0.0

"""Tests of mbtsr.reward: the frozen form against the torch ensemble, closed-form derivatives
against finite differences, the PSD Hessian's properties, the cost's interface, and planning on
a learned quadratic reward against planning on the written quadratic cost (iLQR, CEM, CEM-iLQR,
MPC) on a linear system."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mbtsr.cem import CEMOptions, cem
from mbtsr.cem_ilqr import CEMILQROptions, cem_ilqr
from mbtsr.costs import quadratic_cost
from mbtsr.dynamics import LinearDynamics, rollout
from mbtsr.ilqr import ILQROptions, ilqr
from mbtsr.mpc import MPC, MPCOptions
from mbtsr.reward import FrozenReward, LearnedRewardCost, RewardConfig, RewardModel
from mbtsr.training import holdout_mask

N_X, N_U, DT = 4, 2, 0.1
A = np.block([[np.eye(2), DT * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
B = np.vstack([0.5 * DT**2 * np.eye(2), DT * np.eye(2)])
GOAL = np.array([0.5, -0.3, 0.0, 0.0])
R_WEIGHT = 0.1
X0 = np.array([-0.8, 0.6, 0.0, 0.0])


def quadratic_reward(S: np.ndarray, U: np.ndarray) -> np.ndarray:
    """The reward the model learns: ``-|x - goal|^2 - 0.1 |u|^2``."""
    return -((S - GOAL) ** 2).sum(-1) - R_WEIGHT * (U**2).sum(-1)


def random_frozen(seed: int, n: int = 3, m: int = 2, units: int = 7) -> FrozenReward:
    """Random weights, with an indefinite quadratic term."""
    rng = np.random.default_rng(seed)
    M = rng.standard_normal((n + m, n + m))
    return FrozenReward(rng.standard_normal((n + m, units)), rng.standard_normal(units),
                        rng.standard_normal(units), 0.3, n, P=0.1 * (M + M.T),
                        z0=rng.standard_normal(n + m))


@pytest.fixture(scope="module")
def learned() -> RewardModel:
    """A reward model of the quadratic reward, trained on uniform samples of the box the
    plans stay in."""
    rng = np.random.default_rng(0)
    S = rng.uniform(-1.5, 1.5, (4000, N_X))
    U = rng.uniform(-1.0, 1.0, (4000, N_U))
    model = RewardModel(N_X, N_U, RewardConfig(seed=0))
    model.fit(S, U, quadratic_reward(S, U))
    return model


# ---------------------------------------------------------------------- the model
def test_frozen_form_equals_the_torch_members_mean():
    rng = np.random.default_rng(1)
    S, U = rng.normal(2.0, 3.0, (300, 3)), rng.uniform(-2, 2, (300, 2))
    model = RewardModel(3, 2, RewardConfig(members=3, hidden=8, steps=50, seed=4))
    model.fit(S, U, rng.standard_normal(300))
    mz, sz, mr, sr = model.normalization
    z = torch.as_tensor((np.hstack([S, U]) - mz) / sz, dtype=torch.float32)
    with torch.no_grad():
        members = model._forward(z.expand(3, -1, -1)).double().numpy()
    expected = mr + sr * members.mean(0)
    np.testing.assert_allclose(model.freeze().predict(S, U), expected, rtol=1e-5, atol=1e-5)


def test_fit_is_seeded_and_learns_the_reward(learned):
    rng = np.random.default_rng(5)
    S, U = rng.uniform(-1.5, 1.5, (2000, N_X)), rng.uniform(-1, 1, (2000, N_U))
    r = quadratic_reward(S, U)
    r2 = 1 - np.mean((learned.freeze().predict(S, U) - r) ** 2) / np.var(r)
    assert r2 > 0.99
    small = RewardConfig(members=2, hidden=8, steps=30)
    W = [RewardModel(N_X, N_U, small), RewardModel(N_X, N_U, small),
         RewardModel(N_X, N_U, RewardConfig(members=2, hidden=8, steps=30, seed=1))]
    for model in W:
        model.fit(S[:500], U[:500], r[:500])
    assert np.array_equal(W[0].freeze().W, W[1].freeze().W)
    assert not np.allclose(W[0].freeze().W, W[2].freeze().W)


def test_state_dict_round_trip_continues_identically():
    rng = np.random.default_rng(6)
    S, U = rng.uniform(-1, 1, (300, 2)), rng.uniform(-1, 1, (300, 1))
    r = np.sin(S[:, 0]) - U[:, 0] ** 2
    cfg = RewardConfig(members=2, hidden=8, steps=40, seed=3)
    a = RewardModel(2, 1, cfg)
    a.fit(S, U, r)
    b = RewardModel.from_state_dict(a.state_dict())
    np.testing.assert_array_equal(b.freeze().predict(S, U), a.freeze().predict(S, U))
    a.fit(S, U, r)
    b.fit(S, U, r)  # same minibatches, same weights: the second fit is reproduced exactly
    np.testing.assert_array_equal(b.freeze().predict(S, U), a.freeze().predict(S, U))


def test_early_stopping_ends_before_the_budget_and_keeps_the_best_weights():
    rng = np.random.default_rng(2)
    S, U = rng.uniform(-1, 1, (400, 2)), rng.uniform(-1, 1, (400, 1))
    r = S[:, 0] + 0.5 * U[:, 0] + 0.1 * rng.standard_normal(400)  # noisy: a floor soon met
    cfg = RewardConfig(members=2, hidden=8, steps=20000, eval_every=50, patience=3)
    model = RewardModel(2, 1, cfg)
    fit = model.fit(S, U, r)
    assert fit.steps < cfg.steps and fit.holdout_mse.shape == (2,)
    hold = holdout_mask(400, cfg.holdout)  # the fit's hold-out rows
    mz, sz, mr, sr = model.normalization
    z = torch.as_tensor((np.hstack([S, U])[hold] - mz) / sz, dtype=torch.float32)
    with torch.no_grad():
        pred = mr + sr * model._forward(z.expand(2, -1, -1)).double().numpy()
    np.testing.assert_allclose(((pred - r[hold]) ** 2).mean(1), fit.holdout_mse, rtol=1e-4)


# ---------------------------------------------------------------------- derivatives
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradient_and_exact_hessian_match_finite_differences(seed):
    fr = random_frozen(seed)
    rng = np.random.default_rng(10 + seed)
    x, u = rng.standard_normal((4, 3)), rng.standard_normal((4, 2))
    r, g, H = fr.derivatives(x, u, concave=False)
    np.testing.assert_allclose(r, fr.predict(x, u), rtol=1e-12)
    eps = 1e-5
    for i in range(5):
        e = np.zeros(5)
        e[i] = eps
        rp, gp, _ = fr.derivatives(x + e[:3], u + e[3:], concave=False)
        rm, gm, _ = fr.derivatives(x - e[:3], u - e[3:], concave=False)
        np.testing.assert_allclose(g[:, i], (rp - rm) / (2 * eps), rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(H[:, :, i], (gp - gm) / (2 * eps), rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_cost_hessian_is_psd_and_drops_only_convex_reward_curvature(seed):
    fr = random_frozen(seed, units=12)
    rng = np.random.default_rng(20 + seed)
    x, u = rng.standard_normal((50, 3)), rng.standard_normal((50, 2))
    _, _, H_exact = fr.derivatives(x, u, concave=False)
    _, _, H = fr.derivatives(x, u)
    scale = np.abs(H_exact).max()
    assert np.linalg.eigvalsh(-H).min() >= -1e-12 * scale  # the cost's Hessian is PSD
    assert np.linalg.eigvalsh(H_exact - H).min() >= -1e-12 * scale  # only r-convex terms go
    assert np.linalg.eigvalsh(-H_exact).min() < -1e-3 * scale  # (the exact one is not PSD)


def test_cost_derivatives_match_finite_differences_of_its_total():
    cost = LearnedRewardCost(random_frozen(3), terminal_weight=2.5)
    rng = np.random.default_rng(3)
    T = 5
    X, U = rng.standard_normal((T + 1, 3)), rng.standard_normal((T, 2))
    d = cost.derivatives(X, U)
    eps = 1e-6
    for arr, grad in ((X, d.lx), (U, d.lu)):
        fd = np.zeros_like(arr)
        for idx in np.ndindex(arr.shape):
            step = np.zeros_like(arr)
            step[idx] = eps
            plus = cost.total(X + step, U) if arr is X else cost.total(X, U + step)
            minus = cost.total(X - step, U) if arr is X else cost.total(X, U - step)
            fd[idx] = (plus - minus) / (2 * eps)
        np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-8)
    _, _, H = cost.reward.derivatives(X, np.vstack([U, np.zeros((1, 2))]))
    np.testing.assert_allclose(d.lxx[:T], -H[:T, :3, :3])
    np.testing.assert_allclose(d.lxx[T], -2.5 * H[T, :3, :3])
    np.testing.assert_allclose(d.luu, -H[:T, 3:, 3:])
    np.testing.assert_allclose(d.lux, -H[:T, 3:, :3])
    c = d.convexified()  # already PSD: nothing to project (up to rounding)
    np.testing.assert_allclose(c.lxx, d.lxx, atol=1e-12)
    np.testing.assert_allclose(c.luu, d.luu, atol=1e-12)


# ---------------------------------------------------------------------- the cost interface
def test_values_are_minus_the_predicted_reward_batched():
    fr = random_frozen(4)
    cost = LearnedRewardCost(fr, terminal_weight=0.5, param_dim=6)
    rng = np.random.default_rng(4)
    X, U = rng.standard_normal((7, 4, 3)), rng.standard_normal((7, 3, 2))  # S=7, T=3
    stage = cost.stage_values(X[:, :-1], U, params=np.ones(6))
    np.testing.assert_allclose(stage, -fr.predict(X[:, :-1], U))
    term = cost.terminal_values(X[:, -1], 3, params=np.ones(6))
    np.testing.assert_allclose(term, -0.5 * fr.predict(X[:, -1], np.zeros((7, 2))))
    np.testing.assert_allclose(cost.total(X, U, params=np.ones((2, 6))), stage.sum(1) + term)
    with pytest.raises(ValueError, match="params must be"):
        cost.total(X, U, params=np.ones(5))
    with pytest.raises(ValueError, match="takes no parameters"):
        LearnedRewardCost(fr).total(X, U, params=np.ones(6))


def test_bad_inputs_get_clear_errors():
    fr = random_frozen(5)
    with pytest.raises(ValueError, match="x must have last dimension n=3"):
        fr.predict(np.zeros((2, 4)), np.zeros((2, 2)))
    with pytest.raises(ValueError, match="one batch dim"):
        fr.derivatives(np.zeros((2, 2, 3)), np.zeros((2, 2, 2)))
    with pytest.raises(ValueError, match="P must be symmetric"):
        FrozenReward(fr.W, fr.b, fr.w, 0.0, 3, P=np.triu(np.ones((5, 5))))
    with pytest.raises(TypeError, match="FrozenReward"):
        LearnedRewardCost("not a reward")
    with pytest.raises(ValueError, match="terminal_weight"):
        LearnedRewardCost(fr, terminal_weight=-1.0)
    with pytest.raises(ValueError, match="holdout"):
        RewardConfig(holdout=1.0)
    with pytest.raises(ValueError, match="members"):
        RewardConfig(members=0)
    model = RewardModel(3, 2, RewardConfig(steps=5))
    with pytest.raises(RuntimeError, match="untrained"):
        model.freeze()
    with pytest.raises(ValueError, match="actions must have shape"):
        model.fit(np.zeros((10, 3)), np.zeros((9, 2)), np.zeros(10))
    with pytest.raises(ValueError, match="non-finite"):
        model.fit(np.zeros((10, 3)), np.zeros((10, 2)), np.full(10, np.nan))
    with pytest.raises(ValueError, match="too few for a hold-out"):
        model.fit(np.zeros((2, 3)), np.zeros((2, 2)), np.zeros(2))


# ---------------------------------------------------------------------- planning
def _written_cost(terminal_weight: float):
    return quadratic_cost(np.eye(N_X), R_WEIGHT * np.eye(N_U), GOAL,
                          Qf=terminal_weight * np.eye(N_X))


def _true_total(U: np.ndarray, terminal_weight: float) -> float:
    X = rollout(LinearDynamics(A, B), X0, U)
    return float(_written_cost(terminal_weight).total(X, U))


@pytest.mark.parametrize("planner", ["ilqr", "cem", "cem_ilqr"])
def test_planning_on_a_learned_quadratic_matches_the_written_cost(learned, planner):
    T, tw = 25, 3.0
    model, U0 = LinearDynamics(A, B), np.zeros((T, N_U))
    bounds = {"u_min": -np.ones(N_U), "u_max": np.ones(N_U)}
    solve = {
        "ilqr": lambda c: ilqr(c, model, X0, U0, **bounds, options=ILQROptions(max_iter=100)),
        "cem": lambda c: cem(c, model, X0, U0, **bounds,
                             options=CEMOptions(samples=300, elites=30, iterations=30, seed=1)),
        "cem_ilqr": lambda c: cem_ilqr(c, model, X0, U0, **bounds,
                                       options=CEMILQROptions(max_iter=50)),
    }[planner]
    written = solve(_written_cost(tw))
    res = solve(learned.cost(terminal_weight=tw))
    assert res.status != "failed"
    J_opt, J = _true_total(written.U, tw), _true_total(res.U, tw)
    assert J <= 1.03 * J_opt, (J, J_opt)
    np.testing.assert_allclose(res.X[-1], written.X[-1], atol=0.05)


def test_mpc_on_the_learned_reward_follows_the_written_cost(learned):
    """Closed loop: the learned reward's MPC stays within 0.03 of the written cost's (the
    learned optimum sits about 0.02 from the goal: the fit's gradient error there)."""
    model, final = LinearDynamics(A, B), []
    for cost, pass_obs in ((_written_cost(3.0), False),
                           (learned.cost(terminal_weight=3.0, param_dim=N_X), True)):
        mpc = MPC(ilqr, cost, model, horizon=20, u_min=-1.0, u_max=1.0,
                  options=MPCOptions(iterations_per_step=3))
        x = X0.copy()
        for t in range(60):  # the agent passes the observation as the cost's params
            x = model.step(x, mpc.act(x, t, params=x if pass_obs else None))
        final.append(x)
    np.testing.assert_allclose(final[0], GOAL, atol=0.01)
    np.testing.assert_allclose(final[1], final[0], atol=0.03)

"""Tests of mbtsr.mpc: the receding-horizon controller against finite-horizon LQR, its warm
start and time handling, any optimizer with the shared signature, episodes through the one
rollout loop, and reach-and-hold on the MuJoCo arm with the true model."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from lqr_reference import NaNOffNominal

import envs  # noqa: F401  (registers the envs)
from mbtsr.costs import quadratic_cost
from mbtsr.dynamics import LinearDynamics
from mbtsr.episode import run_episode
from mbtsr.ilqr import ILQROptions, ilqr
from mbtsr.mpc import MPC, MPCOptions

N_X, N_U = 3, 2


def _system():
    A = np.array([[1.0, 0.1, 0.0], [0.0, 1.0, 0.1], [0.05, 0.0, 0.98]])
    B = np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.1]])
    return A, B


def _first_lqr_control(A, B, Q, R, Qf, x, H):
    P = Qf
    for _ in range(H):
        K = -np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        P = Q + A.T @ P @ (A + B @ K)
    return K @ x  # K of the first stage after H backward steps


def test_mpc_action_is_the_first_control_of_finite_horizon_lqr():
    A, B = _system()
    Q, R, Qf = np.eye(N_X), 0.1 * np.eye(N_U), 2 * np.eye(N_X)
    opts = MPCOptions(iterations_per_step=3, optimizer_options=ILQROptions(lambda_init=0.0))
    mpc = MPC(
        ilqr, quadratic_cost(Q, R, np.zeros(N_X), Qf=Qf), LinearDynamics(A, B), horizon=15,
        options=opts,
    )
    x = np.array([1.0, -0.5, 0.7])
    for t in range(5):
        a = mpc.act(x, t)
        np.testing.assert_allclose(a, _first_lqr_control(A, B, Q, R, Qf, x, 15), atol=1e-9)
        x = A @ x + B @ a
    assert len(mpc.compute_times) == 5 and all(c > 0 for c in mpc.compute_times)
    mpc.reset()
    assert mpc.compute_times == [] and mpc.plan is None


def test_cold_start_grows_the_horizon_from_its_own_plans():
    calls = []

    def spy(cost, dynamics, x0, U0, **kw):
        res = ilqr(cost, dynamics, x0, U0, **kw)
        calls.append({"U0": U0.copy(), "U": res.U.copy(), "max_iter": kw["options"]["max_iter"]})
        return res

    A, B = _system()
    mpc = MPC(spy, quadratic_cost(np.eye(N_X), 0.1 * np.eye(N_U), np.array([0.5, 0.0, 0.0])),
              LinearDynamics(A, B), horizon=10, u_min=-1.0, u_max=1.0,
              options=MPCOptions(first_step_iterations=7, cold_start_fractions=(0.25, 0.5)))
    mpc.act(np.zeros(N_X), 0)
    assert [len(c["U0"]) for c in calls] == [2, 5, 10]  # round(2.5) = 2, then 5, then all
    assert [c["max_iter"] for c in calls] == [7, 7, 7]
    np.testing.assert_array_equal(calls[0]["U0"], np.zeros((2, N_U)))
    for prev, nxt in zip(calls[:-1], calls[1:]):  # each extends the last plan by its last control
        k = len(prev["U"])
        np.testing.assert_array_equal(nxt["U0"][:k], prev["U"])
        np.testing.assert_array_equal(nxt["U0"][k:], np.repeat(prev["U"][-1:], len(nxt["U0"]) - k,
                                                               axis=0))
    np.testing.assert_array_equal(mpc.plan, calls[-1]["U"])
    with pytest.raises(ValueError, match="cold_start_fractions"):
        MPCOptions(cold_start_fractions=(0.5, 0.25))
    with pytest.raises(ValueError, match="cold_start_fractions"):
        MPCOptions(cold_start_fractions=(1.0,))


def test_warm_start_shifts_the_previous_plan_and_passes_absolute_time():
    calls = []

    def spy(cost, dynamics, x0, U0, **kw):  # any optimizer with the shared signature
        calls.append({"U0": U0.copy(), "t0": kw["t0"], "max_iter": kw["options"]["max_iter"],
                      "params": kw["params"]})
        return ilqr(cost, dynamics, x0, U0, **kw)

    A, B = _system()
    ref = np.tile(np.array([0.5, 0.0, 0.0]), (40, 1))
    ref[20:, 0] = -0.5
    cost = quadratic_cost(np.eye(N_X), 0.1 * np.eye(N_U))
    mpc = MPC(
        spy,
        cost,
        LinearDynamics(A, B),
        horizon=10,
        u_min=-1.0,
        u_max=1.0,
        options=MPCOptions(iterations_per_step=2, first_step_iterations=7, optimizer_options={},
                           cold_start_fractions=()),
        params=cost.reference(ref),
    )
    x = np.zeros(N_X)
    mpc.act(x, 3)
    plan = mpc.plan.copy()
    mpc.act(x, 4)  # one step later: the plan shifted by one, last control repeated
    np.testing.assert_array_equal(calls[1]["U0"], np.vstack([plan[1:], plan[-1:]]))
    plan = mpc.plan.copy()
    mpc.act(x, 6)  # two steps later
    np.testing.assert_array_equal(calls[2]["U0"], np.vstack([plan[2:], plan[-1:], plan[-1:]]))
    mpc.act(x, 2)  # going back in time: cold start
    np.testing.assert_array_equal(calls[3]["U0"], np.zeros((10, N_U)))
    assert [c["t0"] for c in calls] == [3, 4, 6, 2]
    assert [c["max_iter"] for c in calls] == [7, 2, 2, 7]
    assert all(np.array_equal(c["params"], cost.reference(ref)) for c in calls)
    # the reference is a parameter: the same as a cost built for it
    mpc2 = MPC(ilqr, quadratic_cost(np.eye(N_X), 0.1 * np.eye(N_U), ref), LinearDynamics(A, B),
               horizon=10, u_min=-1.0, u_max=1.0,
               options=MPCOptions(iterations_per_step=2, first_step_iterations=7,
                                  optimizer_options={}, cold_start_fractions=()))
    mpc.reset()
    for t in range(3):
        np.testing.assert_array_equal(mpc.act(x, t), mpc2.act(x, t))


def test_run_mpc_episode_on_the_linear_system_env_equals_receding_horizon_lqr():
    env = gym.make("mbtsr/LinearSystem-v0", n=4, m=2, episode_steps=40, control_cost=0.1)
    u = env.unwrapped
    cost = quadratic_cost(u.cost_Q, u.cost_R, np.zeros(4))
    H = 20
    mpc = MPC(
        ilqr,
        cost,
        u.dynamics_model(),
        horizon=H,
        u_min=-u.action_space.high,
        u_max=u.action_space.high,
        options=MPCOptions(iterations_per_step=2,
                           optimizer_options=ILQROptions(lambda_init=0.0)),
    )
    mpc.act(np.ones(4), 5)  # a stale plan: run_episode resets the controller first
    out = run_episode(env, mpc, seed=3, observe=lambda obs, info: info["state"])
    x, a = out.states, out.actions
    assert x.shape == (41, 4) and a.shape == (40, 2)
    assert out.rewards.shape == (40,) and out.policy_times.shape == (40,)
    assert len(mpc.compute_times) == len(mpc.statuses) == 40
    assert out.truncated and out.T == 40
    # the rewards are the env's: -(x'Qx + u'Ru) on the state after the step
    np.testing.assert_allclose(
        out.rewards, -(np.sum(x[1:] ** 2, 1) + u.cost_R[0, 0] * np.sum(a**2, 1))
    )
    assert np.all(np.abs(a) < u.action_space.high)  # limits inactive: pure LQR
    for t in range(40):
        want = _first_lqr_control(u.A, u.B, u.cost_Q, u.cost_R, u.cost_Q, x[t], H)
        np.testing.assert_allclose(a[t], want, rtol=1e-7, atol=1e-7)
    assert np.linalg.norm(x[-1]) < np.linalg.norm(x[0])


def _reach_and_hold(seed, target, horizon, steps, iterations):
    env = gym.make("mbtsr/TwoLinkArm-v0", episode_steps=steps)
    arm = env.unwrapped
    goal = np.r_[target, 0.0, 0.0]
    cost = quadratic_cost(arm.cost_Q, arm.cost_R)  # the goal is a parameter
    mpc = MPC(
        ilqr,
        cost,
        arm.dynamics_model(),
        horizon=horizon,
        u_min=-1.0,
        u_max=1.0,
        options=MPCOptions(iterations_per_step=iterations, first_step_iterations=30),
        params=cost.reference(goal),
    )
    out = run_episode(env, mpc, seed=seed, options={"target": target},
                      observe=lambda obs, info: info["state"])
    assert np.all(np.abs(out.actions) <= 1.0)
    return out.states - goal


# Bound ("reaches and holds"): the joint angles are within Q_TOL = 0.03 rad of the target at
# the end and during the last 15 steps (the cost's action weight leaves a static offset of a few
# mrad against gravity); the speeds are below QD_TOL = 0.2 rad/s at the end and 0.05 rad/s on
# average over the last 15 steps. Near zero speed MuJoCo's Coulomb friction (a soft stiction
# constraint) makes the speeds chatter by up to ~0.15 rad/s for single steps while the angles
# stay put to a few mrad.
Q_TOL, QD_TOL, QD_MEAN_TOL = 0.03, 0.2, 0.05


def _assert_reached_and_held(err):
    assert np.abs(err[-1, :2]).max() < Q_TOL and np.abs(err[-1, 2:]).max() < QD_TOL
    assert np.abs(err[-15:, :2]).max() < Q_TOL
    assert np.abs(err[-15:, 2:]).mean() < QD_MEAN_TOL


def test_mpc_with_true_mujoco_model_reaches_and_holds_a_target():
    err = _reach_and_hold(seed=0, target=np.array([0.9, -0.7]), horizon=20, steps=50, iterations=2)
    assert np.abs(err[0, :2]).max() > 0.5  # it had somewhere to go
    _assert_reached_and_held(err)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(5))
def test_mpc_with_true_mujoco_model_reaches_and_holds_random_targets(seed):
    rng = np.random.default_rng(100 + seed)
    target = rng.uniform(-1.4, 1.4, 2)
    err = _reach_and_hold(seed=seed, target=target, horizon=50, steps=100, iterations=3)
    assert np.abs(err[0, :2]).max() > 0.2
    _assert_reached_and_held(err)


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        ({"horizon": 0}, ValueError, "horizon must be"),
        ({"u_min": 1.0, "u_max": -1.0}, ValueError, "u_min must be <= u_max"),
        ({"U_init": np.zeros((4, N_U))}, ValueError, r"U_init must have shape \[5, 2\]"),
        ({"options": ILQROptions()}, TypeError, "options must be an instance of MPCOptions"),
        ({"params": np.zeros(4)}, ValueError, r"params must be \[5\] or \[N_ref, 5\]"),
        ({"params": np.full(5, np.nan)}, ValueError, "params contains 5 non-finite"),
        ({"optimizer": "ilqr"}, TypeError, "optimizer must be callable"),
        ({"model": object()}, TypeError, "model must have step"),
        ({"model": LinearDynamics(np.eye(4), np.ones((4, 2)))}, ValueError, "state_dim=4"),
        ({"cost": "quadratic"}, TypeError, "cost must be a mbtsr.costs.CasadiCost"),
    ],
)
def test_bad_construction_arguments(kwargs, exc, match):
    A, B = _system()
    args = {"optimizer": ilqr, "cost": quadratic_cost(np.eye(N_X), np.eye(N_U)),
            "model": LinearDynamics(A, B), "horizon": 5} | kwargs
    with pytest.raises(exc, match=match):
        MPC(**args)


def test_bad_act_arguments():
    A, B = _system()
    mpc = MPC(ilqr, quadratic_cost(np.eye(N_X), np.eye(N_U)), LinearDynamics(A, B), 5)
    with pytest.raises(ValueError, match=r"x must have shape \[3\]"):
        mpc.act(np.zeros(2))
    with pytest.raises(ValueError, match="x contains"):
        mpc.act(np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="t must be"):
        mpc.act(np.zeros(3), -1)
    with pytest.raises(ValueError, match="params must be"):
        mpc.act(np.zeros(3), 0, params=np.zeros(2))
    with pytest.raises(ValueError, match=r"warm_start must have shape \[5, 2\]"):
        mpc.solve(np.zeros(3), warm_start=np.zeros((4, 2)))
    with pytest.raises(ValueError, match="iterations_per_step"):
        MPCOptions(iterations_per_step=0)
    with pytest.raises(TypeError, match="optimizer_options"):
        MPCOptions(optimizer_options=3)


def test_a_model_that_turns_nan_gives_finite_actions_inside_the_box():
    A, B = _system()
    lin = LinearDynamics(A, B)

    cost = quadratic_cost(np.eye(N_X), 0.01 * np.eye(N_U), np.full(N_X, 2.0))
    mpc = MPC(ilqr, cost, NaNOffNominal(A, B, beyond=0.8), 8, u_min=-1.0, u_max=1.0)
    x = np.full(N_X, 0.5)
    for t in range(6):
        a = mpc.act(x, t)
        assert np.isfinite(a).all() and np.all(np.abs(a) <= 1.0)
        x = np.clip(lin.step(x, a), -0.7, 0.7)

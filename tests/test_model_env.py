"""ModelEnv: the frozen learned model as a Gymnasium env.

Checked against independent computations: with the TRUE MuJoCo arm dynamics as the model it
reproduces the real env's observations and rewards; with a linear model its steps are the closed
form ``A x + B clip(u)``; sampled members are one of ``member_predictions``; both env checkers
(Gymnasium's and SB3's) pass on a real (untrained and trained) ensemble.
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env as gym_check_env
from hypothesis import given, settings
from hypothesis import strategies as st
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import envs  # noqa: F401  (registers mbtsr/TwoLinkArm-v0)
from agents.config import AgentConfig
from agents.jacprop_agent import JacPropAgent
from agents.model_env import ModelEnv
from agents.tasks import default_task_for_env
from mbtsr.dynamics import LinearDynamics
from mbtsr.ensemble import DynamicsEnsemble, EnsembleConfig, MemberSpec

torch.set_num_threads(1)
ARM = "mbtsr/TwoLinkArm-v0"

A = np.array([[1.0, 0.1], [-0.2, 0.95]])
B = np.array([[0.0], [0.3]])
OBS = gym.spaces.Box(-np.inf, np.inf, (2,), np.float64)
ACT = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)


def quad_cost(o, a):
    return float(o @ o + 0.1 * a @ a)


def linear_env(**kw) -> ModelEnv:
    kw.setdefault("start_obs", np.array([[1.0, 0.0], [0.0, 1.0], [-0.5, 0.5]]))
    return ModelEnv(LinearDynamics(A, B), OBS, ACT, quad_cost, max_episode_steps=20, **kw)


def ensemble(n=2, m=1, members=3, seed=0) -> DynamicsEnsemble:
    specs = tuple(MemberSpec(activation=a, width=8) for a in ("elu", "tanh", "swish")[:members])
    return DynamicsEnsemble(EnsembleConfig(state_dim=n, action_dim=m, members=specs, seed=seed))


def test_true_arm_model_reproduces_the_real_env():
    env = gym.make(ARM)
    cost, state_map = default_task_for_env(env)
    menv = ModelEnv(
        env.unwrapped.dynamics_model(), env.observation_space, env.action_space,
        lambda o, a: cost(o, a),
        reset_fn=lambda rng: env.reset(seed=int(rng.integers(1000)))[0],
        state_fn=state_map.state, obs_fn=lambda s, o: state_map.observation(s, o),
        max_episode_steps=100,
    )
    obs, _ = env.reset(seed=3)
    mobs, _ = menv.reset(seed=0, options={"obs": obs})
    np.testing.assert_array_equal(mobs, obs)
    actions = np.random.default_rng(1).uniform(-1.2, 1.2, (40, 2)).astype(np.float32)
    for a in actions:  # includes actions outside the box: both clip
        obs, r, term, trunc, _ = env.step(a)
        mobs, mr, mterm, mtrunc, info = menv.step(a)
        np.testing.assert_allclose(mobs, obs, rtol=0, atol=1e-9)
        assert mr == pytest.approx(r, rel=1e-9, abs=1e-12)
        assert (mterm, mtrunc, info["model_diverged"]) == (term, trunc, False)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-5, 5), min_size=1, max_size=6), st.integers(0, 2**31 - 1))
def test_mean_step_is_the_closed_form_with_clipped_actions(us, seed):
    menv = linear_env()
    x, _ = menv.reset(seed=seed)
    assert any(np.array_equal(x, s) for s in menv.start_obs)
    for u in us:
        x_next, r, *_ = menv.step(np.array([u], np.float32))
        uc = float(np.clip(np.float32(u), -1, 1))
        expect = A @ x + B[:, 0] * uc
        np.testing.assert_allclose(x_next, expect, rtol=1e-12, atol=1e-12)
        assert r == pytest.approx(-(expect @ expect + 0.1 * uc * uc), rel=1e-12)
        x = x_next


def test_cost_on_current_observation():
    menv = linear_env(cost_on="current")
    x, _ = menv.reset(seed=0)
    _, r, *_ = menv.step(np.array([0.5], np.float32))
    assert r == pytest.approx(-(x @ x + 0.1 * 0.25))


def test_truncation_termination_and_divergence():
    menv = linear_env()
    menv.reset(seed=0)
    flags = [menv.step(np.zeros(1, np.float32))[2:4] for _ in range(20)]
    assert flags[-1] == (False, True) and all(f == (False, False) for f in flags[:-1])
    menv = linear_env(termination_fn=lambda o, a, o2: abs(o2[0]) > 1.0)
    menv.reset(seed=0, options={"obs": [0.95, 1.0]})
    _, _, term, _, _ = menv.step(np.ones(1, np.float32))
    assert term  # x0' = 0.95 + 0.1 = 1.05
    big = ModelEnv(LinearDynamics(1e300 * np.eye(2), B), OBS, ACT, quad_cost,
                   start_obs=np.full((1, 2), 1e-150))
    x, _ = big.reset(seed=0)
    x1, *_ = big.step(np.zeros(1, np.float32))
    with np.errstate(over="ignore"):
        x2, r, term, trunc, info = big.step(np.zeros(1, np.float32))
    assert term and info["model_diverged"] and np.array_equal(x2, x1) and np.isfinite(r)


@pytest.mark.parametrize("member", ["step", "episode"])
def test_sampled_members_are_seeded_members(member):
    model = ensemble()
    menv = ModelEnv(model, OBS, ACT, quad_cost, start_obs=np.array([[0.3, -0.2]]),
                    member=member, max_episode_steps=30)
    actions = np.random.default_rng(0).uniform(-1, 1, (30, 1)).astype(np.float32)

    def run(seed):
        x, _ = menv.reset(seed=seed)
        chosen = []
        for a in actions:
            preds = model.member_predictions(x, a.astype(float))
            x, *_ = menv.step(a)
            hits = [k for k in range(3) if np.allclose(preds[k], x, rtol=0, atol=1e-12)]
            assert len(hits) == 1  # the next state is exactly one member's prediction
            chosen.append(hits[0])
        return chosen

    first = run(7)
    assert run(7) == first  # same seed, same members
    if member == "episode":
        assert len(set(first)) == 1
        assert len({run(s)[0] for s in range(12)}) > 1
    else:
        assert len(set(first)) > 1


def check_both(menv: ModelEnv) -> None:
    """Both checkers pass; the only warnings are about the (real env's) unbounded obs space."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        gym_check_env(menv, skip_render_check=True)
        sb3_check_env(menv, warn=True)
    other = [str(w.message) for w in caught if "infinity" not in str(w.message)]
    assert other == []


def test_checkers_pass_on_a_real_ensemble():
    for member in ("mean", "step", "episode"):
        menv = ModelEnv(ensemble(), OBS, ACT, quad_cost, start_obs=np.array([[0.3, -0.2]]),
                        member=member, max_episode_steps=10)
        check_both(menv)


def test_from_agent_uses_the_agents_model_cost_and_spaces():
    env = gym.make(ARM)
    cfg = AgentConfig.default({"model.ensemble_size": 2, "evaluation.every": 0},
                              progress=False, tensorboard=False, checkpoint=False)
    agent = JacPropAgent(env, cfg)
    menv = ModelEnv.from_agent(agent)
    check_both(menv)
    obs, _ = menv.reset(seed=5)
    real_obs, _ = env.reset(seed=int(np.random.default_rng(5).integers(2**31 - 1)))
    np.testing.assert_array_equal(obs, real_obs)  # drawn from the env's reset distribution
    a = np.array([0.3, -0.4], np.float32)
    nxt, r, *_ = menv.step(a)
    x_next = agent.model.freeze().step(obs[:4], a.astype(float))  # the planner's float32 kernels
    np.testing.assert_allclose(nxt, np.concatenate([x_next, obs[4:]]), rtol=0, atol=1e-12)
    x_ref = agent.model.step(obs[:4], a.astype(float))  # the float64 reference
    np.testing.assert_allclose(x_next, x_ref, rtol=0, atol=1e-6 * np.abs(x_ref).max())
    cost, _ = default_task_for_env(env)
    assert r == pytest.approx(-float(cost(nxt, a.astype(float))), rel=1e-12)
    assert menv.max_episode_steps == agent.spec.episode_steps


def test_bad_arguments_are_named():
    lin = LinearDynamics(A, B)
    start = np.zeros((1, 2))
    with pytest.raises(ValueError, match="exactly one of start_obs and reset_fn"):
        ModelEnv(lin, OBS, ACT, quad_cost)
    with pytest.raises(ValueError, match="member"):
        ModelEnv(lin, OBS, ACT, quad_cost, start_obs=start, member="episode")  # no members
    with pytest.raises(ValueError, match="start_obs"):
        ModelEnv(lin, OBS, ACT, quad_cost, start_obs=np.zeros((1, 3)))
    with pytest.raises(ValueError, match="action_space"):
        ModelEnv(lin, OBS, gym.spaces.Box(-np.inf, np.inf, (1,)), quad_cost, start_obs=start)
    with pytest.raises(ValueError, match="max_episode_steps"):
        ModelEnv(lin, OBS, ACT, quad_cost, start_obs=start, max_episode_steps=0)
    with pytest.raises(TypeError, match="model"):
        ModelEnv(object(), OBS, ACT, quad_cost, start_obs=start)
    menv = ModelEnv(lin, OBS, ACT, quad_cost, start_obs=start)
    with pytest.raises(RuntimeError, match="reset"):
        menv.step(np.zeros(1))
    menv.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        menv.step(np.array([np.nan]))


def test_from_agent_takes_the_tasks_termination_fn():
    env = gym.make(ARM)
    cfg = AgentConfig.default({"model.ensemble_size": 2, "evaluation.every": 0},
                              progress=False, tensorboard=False, checkpoint=False)
    agent = JacPropAgent(env, cfg,
                         termination_fn=lambda obs: np.abs(obs[..., 0]) > 0.5)
    menv = ModelEnv.from_agent(agent)
    obs, _ = menv.reset(seed=0, options={"obs": [0.5, 0, 0, 0, 0.3, 0.2]})
    for a in np.random.default_rng(0).uniform(-1, 1, (20, 2)).astype(np.float32):
        nxt, _, term, _, _ = menv.step(a)
        assert term == (abs(nxt[0]) > 0.5)  # the task's function on the next observation
        if term:
            obs, _ = menv.reset(seed=0, options={"obs": [0.5, 0, 0, 0, 0.3, 0.2]})

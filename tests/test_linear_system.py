"""Tests of mbtsr/LinearSystem-v0 and the paper's random stable system (Algorithm 2)."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
import scipy.linalg
from gymnasium.utils.env_checker import check_env
from hypothesis import given, settings
from hypothesis import strategies as st

import envs  # noqa: F401  (registration)
from envs.linear_system import LinearSystemEnv, random_stable_system
from mbtsr.dynamics import DynamicsModel, LinearDynamics


def test_gymnasium_and_sb3_env_checkers_pass():
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    check_env(LinearSystemEnv(), skip_render_check=True)
    sb3_check_env(LinearSystemEnv(), warn=True)
    env = gym.make("mbtsr/LinearSystem-v0", n=4, m=2)
    check_env(env.unwrapped, skip_render_check=True)
    assert env.observation_space.shape == (4,) and env.action_space.shape == (2,)


@settings(max_examples=30, deadline=None)
@given(
    n=st.integers(1, 12),
    m=st.integers(1, 4),
    dt=st.floats(1e-3, 0.2),
    seed=st.integers(0, 2**32 - 1),
)
def test_every_eigenvalue_has_modulus_exp_minus_dt_squared(n, m, dt, seed):
    a_mat, b_mat = random_stable_system(n, m, dt, seed)
    assert a_mat.shape == (n, n) and b_mat.shape == (n, m)
    np.testing.assert_allclose(np.abs(np.linalg.eigvals(a_mat)), math.exp(-(dt**2)), rtol=1e-9)
    # A = expm(dt (S - dt I)) with S skew, so A^T A = exp(-2 dt^2) I (a scaled rotation)
    np.testing.assert_allclose(a_mat.T @ a_mat, math.exp(-2 * dt**2) * np.eye(n), atol=1e-10)


def test_construction_follows_algorithm_2_with_the_documented_draw_order():
    dt = 0.02
    a_mat, b_mat = random_stable_system(10, 10, dt, seed=1)
    rng = np.random.default_rng(1)
    a0 = rng.standard_normal((10, 10))
    b_expected = dt * rng.standard_normal((10, 10))
    np.testing.assert_allclose(a_mat, scipy.linalg.expm(dt * (a0 - a0.T - dt * np.eye(10))))
    np.testing.assert_array_equal(b_mat, b_expected)
    # B / dt is standard normal: over 50x50 entries mean and std within 5 standard errors
    _, b_big = random_stable_system(50, 50, dt, seed=3)
    z = b_big / dt
    assert abs(z.mean()) < 5 / 50
    assert abs(z.std() - 1) < 5 * (1 / math.sqrt(2 * 2500))


def test_linearize_is_a_b_everywhere_and_dynamics_model_matches_env_steps():
    env = LinearSystemEnv(n=6, m=3, system_seed=4)
    a_lin, b_lin = env.linearize(np.ones(6), np.ones(3))
    np.testing.assert_array_equal(a_lin, env.A)
    np.testing.assert_array_equal(b_lin, env.B)
    rng = np.random.default_rng(0)
    xs, us = rng.standard_normal((7, 6)), rng.standard_normal((7, 3))
    a_traj, b_traj = env.linearize_trajectory(xs, us)
    np.testing.assert_array_equal(a_traj, np.broadcast_to(env.A, (7, 6, 6)))
    np.testing.assert_array_equal(b_traj, np.broadcast_to(env.B, (7, 6, 3)))
    model = env.dynamics_model()
    assert isinstance(model, LinearDynamics) and isinstance(model, DynamicsModel)
    for x, u in zip(xs, us):
        env.reset(options={"state": x})
        nxt = env.step(u)[4]["state"]
        np.testing.assert_allclose(nxt, model.step(x, u), rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(nxt, env.A @ x + env.B @ u, rtol=1e-14, atol=1e-14)


def test_reward_start_state_truncation_and_clipping():
    env = LinearSystemEnv(n=3, m=2, episode_steps=4, action_bound=2.0, control_cost=0.1)
    obs, info = env.reset(seed=5)
    np.testing.assert_array_equal(obs, np.random.default_rng(5).standard_normal(3))
    np.testing.assert_array_equal(info["state"], obs)
    x = obs
    for t in range(4):
        u = np.array([3.0, -0.5])  # 3.0 is clipped to 2.0
        obs, reward, terminated, truncated, info = env.step(u)
        applied = np.array([2.0, -0.5])
        expected_x = env.A @ x + env.B @ applied
        np.testing.assert_allclose(obs, expected_x, rtol=1e-14)
        assert reward == pytest.approx(-(expected_x @ expected_x + 0.1 * applied @ applied))
        assert not terminated and truncated == (t == 3)
        x = obs


def test_same_seeds_give_bit_identical_systems_and_trajectories():
    def run(system_seed: int, seed: int) -> np.ndarray:
        env = gym.make("mbtsr/LinearSystem-v0", system_seed=system_seed)
        obs, _ = env.reset(seed=seed)
        out = [obs]
        for u in np.random.default_rng(seed).standard_normal((20, 10)):
            out.append(env.step(u)[0])
        return np.array(out)

    np.testing.assert_array_equal(run(1, 3), run(1, 3))
    assert not np.array_equal(run(1, 3), run(2, 3))
    assert not np.array_equal(run(1, 3), run(1, 4))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"dt": 0.0}, "dt"),
        ({"dt": -0.1}, "dt"),
        ({"dt": float("nan")}, "dt"),
        ({"n": 0}, "n must be"),
        ({"m": 1.5}, "m must be"),
        ({"action_bound": 0.0}, "action_bound"),
        ({"episode_steps": 0}, "episode_steps"),
    ],
)
def test_bad_constructor_arguments_raise_value_error(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LinearSystemEnv(**kwargs)


def test_bad_actions_and_states_raise_value_error():
    env = LinearSystemEnv(n=3, m=2)
    env.reset(seed=0)
    for bad in (np.zeros(3), np.zeros((2, 1)), np.array([np.nan, 0.0]), np.array([np.inf, 0.0])):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    with pytest.raises(ValueError, match="state"):
        env.reset(options={"state": np.zeros(4)})
    with pytest.raises(ValueError, match="x"):
        env.linearize(np.zeros(2), np.zeros(2))

"""Tests of mbtsr.episode.run_episode, the one env-rollout loop: it equals stepping the env by
hand, clips and records exactly what the env receives, threads SB3 recurrent state, stops on
request, and names bad arguments."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import envs  # noqa: F401  (registers the envs)
from mbtsr.episode import as_policy, run_episode

LIN = "mbtsr/LinearSystem-v0"


def _by_hand(env, U, seed):
    obs, info = env.reset(seed=seed)
    X, R = [info["state"].copy()], []
    for a in U:
        obs, r, term, trunc, info = env.step(np.clip(a, env.action_space.low,
                                                     env.action_space.high))
        X.append(info["state"].copy())
        R.append(r)
        if term or trunc:
            break
    return np.array(X), np.array(R)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**16), T=st.integers(1, 12), scale=st.floats(0.1, 30.0))
def test_equals_stepping_the_env_by_hand_and_records_the_clipped_actions(seed, T, scale):
    env = gym.make(LIN, n=3, m=2, episode_steps=8)
    U = scale * np.random.default_rng(seed).standard_normal((T, 2))
    rec = run_episode(env, lambda obs, t: U[t], seed=seed, max_steps=T)
    X, R = _by_hand(env, U, seed)
    np.testing.assert_array_equal(rec.states, X)
    np.testing.assert_array_equal(rec.rewards, R)
    assert rec.T == min(T, 8) and rec.truncated == (T >= 8)
    high = env.action_space.high
    np.testing.assert_array_equal(rec.actions, np.clip(U[:rec.T], -high, high))
    assert rec.policy_times.shape == (rec.T,) and rec.cost == pytest.approx(-R.sum())


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**16), cut=st.integers(1, 7))
def test_start_continues_an_episode_as_if_it_had_not_stopped(seed, cut):
    """Two calls, the second from the first's last ``(obs, info)``, equal one call: the states,
    rewards and the TimeLimit's truncation at 8 steps (the env's step count carries on)."""
    env = gym.make(LIN, n=3, m=2, episode_steps=8)
    U = np.random.default_rng(seed).uniform(-1, 1, (10, 2))
    whole = run_episode(env, lambda obs, t: U[t], seed=seed)
    first = run_episode(env, lambda obs, t: U[t], seed=seed, max_steps=cut)
    rest = run_episode(env, lambda obs, t: U[cut + t], seed=None,
                       start=(first.obs[-1], first.info))
    np.testing.assert_array_equal(np.concatenate([first.states, rest.states[1:]]), whole.states)
    np.testing.assert_array_equal(np.concatenate([first.rewards, rest.rewards]), whole.rewards)
    assert not first.truncated and rest.truncated and first.T + rest.T == 8


def test_observe_stop_reset_and_sb3_state_threading():
    env = gym.make(LIN, n=2, m=1, episode_steps=30)
    seen = []

    class Policy:
        resets = 0

        def reset(self):
            Policy.resets += 1

        def __call__(self, y, t):
            seen.append(y.copy())
            return np.array([0.1])

    rec = run_episode(env, Policy(), seed=1, observe=lambda obs, info: 2.0 * info["state"],
                      stop=lambda y: np.abs(y).max() > 1e9 or len(seen) == 4)
    assert Policy.resets == 1 and rec.stopped and rec.T == 4
    np.testing.assert_array_equal(np.array(seen), 2.0 * rec.states[:4])

    class SB3Like:
        def predict(self, obs, state=None, episode_start=None, deterministic=True):
            k = 0 if state is None else state + 1
            return np.array([0.01 * k]), k

    rec = run_episode(env, SB3Like(), seed=2, max_steps=5)
    np.testing.assert_allclose(rec.actions[:, 0], 0.01 * np.arange(5))


@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        ({"policy": 3}, TypeError, "policy must be a callable"),
        ({"max_steps": -1}, ValueError, "max_steps must be"),
        ({"max_steps": 2.5}, ValueError, "max_steps must be"),
        ({"seed": "a"}, ValueError, "seed must be"),
        ({"observe": 1}, TypeError, "observe must be callable"),
        ({"stop": "x"}, TypeError, "stop must be callable"),
        ({"start": np.zeros(2)}, TypeError, "start must be None or the .obs, info. pair"),
        ({"start": (np.zeros(2), {}, 0)}, TypeError, "got a tuple of 3"),
        ({"start": (np.zeros(2), None)}, TypeError, "got info of type NoneType"),
    ],
)
def test_bad_arguments_are_named(kwargs, exc, match):
    env = gym.make(LIN, n=2, m=1)
    args = {"policy": lambda obs, t: np.zeros(1), "seed": 0} | kwargs
    with pytest.raises(exc, match=match):
        run_episode(env, **args)
    with pytest.raises(ValueError, match="1-D Box"):
        run_episode(gym.make("CartPole-v1"), lambda obs, t: 0, seed=0)
    with pytest.raises(TypeError, match="policy must be"):
        as_policy(None)


@pytest.mark.parametrize("action", [np.zeros(2), np.array([np.nan]), np.array([np.inf])])
def test_a_bad_action_from_the_policy_is_named_with_its_step(action):
    env = gym.make(LIN, n=2, m=1)
    with pytest.raises(ValueError, match=r"returned action .* at step 3; .* finite \[1\]"):
        run_episode(env, lambda obs, t: action if t == 3 else np.zeros(1), seed=0)

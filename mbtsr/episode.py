"""The one env-rollout loop, :func:`run_episode` (evaluation, data collection, MPC episodes,
video): any Gymnasium env, a policy ``(obs, t) -> action`` or anything with SB3's ``predict``;
the action is clipped into the space and the env gets exactly the recorded action.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from mbtsr.validation import check_int

__all__ = ["EpisodeRecord", "as_policy", "run_episode"]

Policy = Callable[[np.ndarray, int], np.ndarray]


@dataclass
class EpisodeRecord:
    """One episode in a real env.

    ``obs: [T+1, obs_dim]``, ``actions: [T, m]`` (as applied, after clipping), ``rewards: [T]``;
    ``states: [T+1, k]`` the env's ``info["state"]`` when it reports one; ``frames`` rendered
    images (``render=True``); ``policy_times: [T]`` seconds the policy took per step and the
    totals ``time_policy``/``time_env``; ``terminated``/``truncated`` as the env said,
    ``stopped`` if ``stop`` ended it; ``info0`` the first info (the reset's, or ``start``'s),
    ``info`` the last.
    """

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    states: np.ndarray | None
    terminated: bool
    truncated: bool = False
    stopped: bool = False
    info0: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    frames: list = field(default_factory=list)
    policy_times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    time_policy: float = 0.0
    time_env: float = 0.0

    @property
    def cost(self) -> float:
        """Episode cost ``-sum(rewards)``."""
        return float(-np.sum(self.rewards))

    @property
    def T(self) -> int:  # noqa: N802
        return self.actions.shape[0]


def as_policy(policy: Any) -> Policy:
    """``policy`` as a step function ``(obs, t) -> action``.

    Accepts a callable ``(obs, t) -> action`` or an object with Stable-Baselines3's
    ``predict(obs, state, episode_start, deterministic)`` (its recurrent state is threaded
    through the episode; ``t == 0`` starts a new one).
    """
    if hasattr(policy, "predict"):
        holder: dict[str, Any] = {"state": None}

        def act(obs: np.ndarray, t: int) -> np.ndarray:
            action, holder["state"] = policy.predict(
                obs, state=None if t == 0 else holder["state"],
                episode_start=np.array([t == 0]), deterministic=True,
            )
            return np.asarray(action, dtype=float).reshape(-1)

        return act
    if callable(policy):
        return policy
    raise TypeError(f"policy must be a callable (obs, t) -> action or have a predict(obs, state, "
                    f"episode_start, deterministic) method, got {type(policy).__name__}")


def run_episode(
    env: gym.Env,
    policy: Any,
    *,
    seed: int | None,
    options: dict | None = None,
    max_steps: int | None = None,
    render: bool = False,
    observe: Callable[[Any, dict], np.ndarray] | None = None,
    stop: Callable[[np.ndarray], bool] | None = None,
    start: tuple[Any, dict] | None = None,
) -> EpisodeRecord:
    """Reset ``env`` (or continue its episode from ``start``) and run ``policy`` until
    termination, truncation, ``max_steps`` or ``stop``.

    :param env: a Gymnasium env with a 1-D ``Box`` action space.
    :param policy: ``(y, t) -> action`` or an SB3-style object (see :func:`as_policy`); ``y``
        is ``observe(obs, info)`` (default: the observation). A policy with a ``reset()``
        method (e.g. :class:`mbtsr.mpc.MPC`) is reset first.
    :param seed: reset seed (``None``: the env's own stream).
    :param options: passed to ``env.reset`` (e.g. ``{"target": ...}``).
    :param max_steps: stop after this many steps (``None``: the env's own limit).
    :param render: record ``env.render()`` before the first and after every step.
    :param observe: ``(obs, info) -> y`` what the policy and ``stop`` see.
    :param stop: ``stop(y) -> bool`` checked on every ``y`` (the first included); true ends
        the episode with ``stopped=True``.
    :param start: ``(obs, info)`` where an earlier call stopped at ``max_steps`` (neither
        terminated nor truncated, and ``env`` not used since): continue that episode of ``env``
        from there instead of resetting (``seed`` and ``options`` are unused, ``info0`` is
        this ``info``; ``t`` counts from 0 again and the policy starts anew, as at a reset).
    :return: :class:`EpisodeRecord`.
    """
    space = env.action_space
    if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
        raise ValueError(f"env.action_space must be a 1-D Box, got {space}")
    if max_steps is not None:
        check_int("max_steps", max_steps, 0)
    if seed is not None:
        check_int("seed", seed, None)
    for name, fn in (("observe", observe), ("stop", stop)):
        if fn is not None and not callable(fn):
            raise TypeError(f"{name} must be callable or None, got {type(fn).__name__}")
    if start is not None:
        what = None
        if not isinstance(start, tuple):
            what = type(start).__name__
        elif len(start) != 2:
            what = f"a tuple of {len(start)}"
        elif not isinstance(start[1], dict):
            what = f"info of type {type(start[1]).__name__}"
        if what is not None:
            raise TypeError("start must be None or the (obs, info) pair of the env's running "
                            f"episode, got {what}")
    act = as_policy(policy)
    if callable(getattr(policy, "reset", None)) and not hasattr(policy, "predict"):
        policy.reset()
    low, high, m = space.low, space.high, space.shape[0]
    if start is None:
        obs, info = env.reset(seed=None if seed is None else int(seed), options=options)
    else:
        obs, info = start
    info0 = dict(info)
    obs_list, act_list, rew_list, times = [np.asarray(obs, dtype=float)], [], [], []
    states = [np.array(info["state"], dtype=float)] if "state" in info else None
    frames = [np.asarray(env.render()).copy()] if render else []
    t_env = 0.0
    terminated = truncated = False
    t = 0
    while True:
        y = obs if observe is None else observe(obs, info)
        stopped = stop is not None and bool(stop(y))
        if stopped or terminated or truncated or (max_steps is not None and t >= max_steps):
            break
        tic = time.perf_counter()
        a = np.asarray(act(y, t), dtype=float)
        times.append(time.perf_counter() - tic)
        if a.size != m or not np.isfinite(a).all():
            raise ValueError(
                f"the policy returned action {a.tolist()} at step {t}; the env needs a finite "
                f"[{m}] action"
            )
        a = np.clip(a.reshape(m), low, high)
        a_env = a.astype(space.dtype)  # the env receives exactly the recorded action
        tac = time.perf_counter()
        obs, reward, terminated, truncated, info = env.step(a_env)
        t_env += time.perf_counter() - tac
        obs_list.append(np.asarray(obs, dtype=float))
        act_list.append(a_env.astype(float))
        rew_list.append(float(reward))
        if states is not None:
            states.append(np.array(info["state"], dtype=float))
        if render:
            frames.append(np.asarray(env.render()).copy())
        t += 1
    return EpisodeRecord(
        obs=np.asarray(obs_list),
        actions=np.asarray(act_list, dtype=float).reshape(-1, m),
        rewards=np.asarray(rew_list),
        states=None if states is None else np.asarray(states, dtype=float),
        terminated=bool(terminated),
        truncated=bool(truncated),
        stopped=stopped,
        info0=info0,
        info=dict(info),
        frames=frames,
        policy_times=np.asarray(times),
        time_policy=float(np.sum(times)),
        time_env=t_env,
    )

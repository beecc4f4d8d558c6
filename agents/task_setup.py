"""The agent's task from its constructor arguments: the cost and the observation <-> model-state
maps (given, saved with a checkpoint, or the env's own), checked on probe observations before
any learning starts, so that a wrong function fails at construction with a clear message.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from agents.tasks import EnvSpec, QuadraticTargetCost, StateMap, default_task_for_env
from mbtsr.validation import call_user_fn, check_callable

__all__ = ["check_state_map", "checked_termination_fn", "probe_observations", "resolve_task"]


def resolve_task(
    env: gym.Env | None,
    cost_fn: Callable | None,
    state_fn: Callable | None,
    obs_fn: Callable | None,
    saved_task: dict | None = None,
) -> tuple[Any, StateMap]:
    """``(cost_fn, state_map)``: the given functions, else the saved task's (a checkpoint's
    ``to_dict()`` of a :class:`~agents.tasks.QuadraticTargetCost` and a
    :class:`~agents.tasks.StateMap`), else the env's own quadratic cost.

    :raises ValueError: no cost given and none saved or built into the env.
    """
    if cost_fn is None and saved_task is not None and saved_task.get("cost") is not None:
        cost_fn = QuadraticTargetCost.from_dict(saved_task["cost"])
        if state_fn is None and saved_task.get("state_map") is not None:
            return cost_fn, StateMap.from_dict(saved_task["state_map"])
        return cost_fn, StateMap(state_fn, obs_fn)
    if cost_fn is None:
        default = default_task_for_env(env) if env is not None else None
        if default is None:
            env_id = getattr(getattr(env, "spec", None), "id", None)
            where = "the saved agent" if env is None else f"env {env_id or env!r}"
            raise ValueError(
                f"cost_fn is required: {where} has no built-in cost (env.unwrapped.cost_Q "
                "and cost_R); pass cost_fn(obs, action) written with casadi operations"
            )
        cost_fn, default_map = default
        return cost_fn, default_map if state_fn is None else StateMap(state_fn, obs_fn)
    return cost_fn, StateMap(state_fn, obs_fn)


def probe_observations(env: gym.Env | None, shape: tuple[int, ...]) -> np.ndarray:
    """Seeded test observations ``shape = [..., obs_dim]`` in ``[-1, 1]``, clipped to the
    env's observation space when there is an env."""
    probe = np.random.default_rng(0).uniform(-1.0, 1.0, shape)
    if env is not None:
        probe = np.clip(probe, env.observation_space.low, env.observation_space.high)
    return probe


def check_state_map(state_map: StateMap, env: gym.Env | None, spec: EnvSpec) -> np.ndarray:
    """Call the state map on one observation and on a batch of three (it is called on whole
    episodes ``[T+1, obs_dim]``) and check that the batch gives the rows of the single calls.

    :return: the state of the first probe ``[n]``.
    :raises ValueError: a map that fails, returns no 1-D state or maps a batch differently.
    """
    probe = probe_observations(env, (3, spec.obs_dim))
    single = call_user_fn(
        lambda: [state_map.state(o) for o in probe],
        failure=f"state_fn failed on one observation [{spec.obs_dim}]",
    )
    s = single[0]
    if s.ndim != 1 or s.size < 1:
        raise ValueError(f"state_fn(obs) must return a 1-D state, got shape {list(s.shape)}")
    batch = call_user_fn(
        state_map.state, probe,
        failure="state_fn must also accept a batch of observations [B, obs_dim] and return "
        f"[B, n] (it is applied to whole episodes); it failed on [3, {spec.obs_dim}]",
    )
    if batch.shape != (3, s.size) or not np.allclose(batch, np.stack(single), equal_nan=True):
        raise ValueError(
            "state_fn must map a batch of observations [B, obs_dim] row by row to "
            f"[B, n={s.size}] (it is applied to whole episodes); for a batch of 3 it "
            f"returned shape {list(batch.shape)}"
            + ("" if batch.shape != (3, s.size) else " with rows that differ from "
               "state_fn applied to each observation")
            + " -- use obs[..., i] indexing (numpy) instead of obs[i]"
        )
    return s


def checked_termination_fn(
    fn: Callable[[np.ndarray], np.ndarray] | None, env: gym.Env | None, spec: EnvSpec
) -> Callable[[np.ndarray], np.ndarray] | None:
    """``fn`` after checking it on a batch of observations ``[2, 3, obs_dim] -> bool [2, 3]``.

    :raises ValueError: not callable, fails on a batch, or returns another shape.
    """
    if fn is None:
        return None
    check_callable("termination_fn", fn, "obs -> bool")
    out = np.asarray(call_user_fn(
        fn, probe_observations(env, (2, 3, spec.obs_dim)),
        failure=f"termination_fn must accept a batch of observations [..., "
        f"obs_dim={spec.obs_dim}]; it failed on [2, 3, {spec.obs_dim}]",
    ))
    if out.shape != (2, 3):
        raise ValueError(
            f"termination_fn(obs [..., obs_dim]) must return one bool per observation [...]; for "
            f"[2, 3, {spec.obs_dim}] it returned shape {list(out.shape)}")
    return fn

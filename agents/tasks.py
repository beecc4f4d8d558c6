"""Reusable task definitions: an env id, a cost on ``(observation, action)`` written as a user
would (the env's own reward terms, with CasADi operations), and the env's termination rule.

A task is data (:class:`Task`) that the agent, the true-model oracle, the benchmark suite, the
SB3 baselines and the PETS peer all consume unchanged (a task's ``state_fn``/``obs_fn``, the
agent's model state, concern the agent alone: SB3, PETS and the small-data study work on the
observation)::

    from agents import AgentConfig, JacPropAgent
    from agents.tasks import pusher

    task = pusher()
    env = task.make_env()
    agent = JacPropAgent(env, AgentConfig(), **task.agent_kwargs())

Conventions shared by every task here:

* ``cost_fn(obs, action)`` is the NEGATED per-step reward of the env, computed from the
  observation the env returns after the step and the action. Where the reward uses a quantity
  the observation does not hold exactly (a body position from before the last substep), the
  cost uses the observation's closest equivalent and says so.
* Envs with an alive bonus (the inverted pendulums) terminate when the pole falls and then pay
  no more; their cost subtracts the bonus, so that staying alive is cheaper than ending (a
  planner that drops the costs after a predicted termination would otherwise prefer to fall).
* ``termination_fn(obs)`` is numpy, batched ``obs [..., obs_dim] -> bool [...]``, the env's own
  rule on the observation.
* Norms in rewards are smoothed (``sqrt(|v|^2 + 1e-4)``) so that gradients exist at 0.

The functions take no arguments but the env's constructor keywords (``**make``), so a user
starts from a task and changes what the env offers (``inverted_pendulum(max_episode_steps=200)``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

__all__ = [
    "Task",
    "TASKS",
    "half_cheetah",
    "inverted_double_pendulum",
    "inverted_pendulum",
    "make_task",
    "pusher",
    "reacher",
    "two_link_arm",
]


@dataclass(frozen=True)
class Task:
    """A control task on a Gymnasium env.

    :param name: short name (``"pusher"``).
    :param env_id: the registered Gymnasium id (``"Pusher-v5"``).
    :param make_kwargs: keyword arguments of ``gymnasium.make``.
    :param cost_fn: ``(obs [obs_dim], action [act_dim]) -> scalar`` in CasADi operations, or
        ``None`` for envs that define their own cost (``mbtsr/TwoLinkArm-v0``).
    :param terminal_cost_fn: ``obs -> scalar`` (CasADi) on the last predicted observation of a
        plan, or ``None`` (the stage cost at zero action).
    :param termination_fn: ``obs [..., obs_dim] -> bool [...]`` (numpy), or ``None``.
    :param state_fn: ``obs [..., obs_dim] -> state [..., n]`` (numpy): the model's state, when
        it should not be the observation itself; ``None``: the observation.
    :param obs_fn: ``(state [n], obs_ref [obs_dim]) -> obs`` (CasADi), the inverse of
        ``state_fn`` for the cost (``obs_ref`` supplies what the state leaves out).
    """

    name: str
    env_id: str
    make_kwargs: dict[str, Any] = field(default_factory=dict)
    cost_fn: Callable[[Any, Any], Any] | None = None
    terminal_cost_fn: Callable[[Any], Any] | None = None
    termination_fn: Callable[[np.ndarray], np.ndarray] | None = None
    state_fn: Callable[[np.ndarray], np.ndarray] | None = None
    obs_fn: Callable[[Any, Any], Any] | None = None

    def make_env(self, **overrides: Any):
        """``gymnasium.make(env_id, **make_kwargs, **overrides)`` (``mbtsr/`` ids registered)."""
        import gymnasium as gym

        if self.env_id.startswith("mbtsr/"):
            import envs  # noqa: F401  (registers the mbtsr/ ids)
        return gym.make(self.env_id, **{**self.make_kwargs, **overrides})

    def agent_kwargs(self) -> dict[str, Any]:
        """The task's functions as keyword arguments of :class:`agents.JacPropAgent` (and of
        :func:`agents.evaluation.oracle_policy`)."""
        return {"cost_fn": self.cost_fn, "terminal_cost_fn": self.terminal_cost_fn,
                "termination_fn": self.termination_fn, "state_fn": self.state_fn,
                "obs_fn": self.obs_fn}

    def observation_cost(self) -> Callable[[Any, Any], Any]:
        """The cost on ``(obs, action)`` in CasADi operations: ``cost_fn``, or for an env that
        states its own quadratic cost (``env.unwrapped.cost_Q``/``cost_R``, as
        ``mbtsr/TwoLinkArm-v0``) that cost (:class:`agents.task.QuadraticTargetCost`, the one
        the agent builds for it): what peers outside mbtsr score plans with.

        :raises ValueError: if the task has no ``cost_fn`` and its env states no cost.
        """
        if self.cost_fn is not None:
            return self.cost_fn
        from agents.task import default_task_for_env

        env = self.make_env()
        try:
            found = default_task_for_env(env)
        finally:
            env.close()
        if found is None:
            raise ValueError(f"task {self.name!r} has no cost_fn and its env states no cost "
                             "(env.unwrapped.cost_Q/cost_R)")
        return found[0]


def _smooth_norm(v: Any) -> Any:
    return ca.sqrt(ca.sumsqr(v) + 1e-4)


# ---- Reacher-v5
def _reacher_cost(obs, a):
    """Reacher-v5: ``|fingertip - target| + |a|^2`` (``obs[8:10]`` is fingertip - target)."""
    return _smooth_norm(obs[8:10]) + ca.sumsqr(a)


def _reacher_terminal(obs):
    """Be at the target at the end of every plan."""
    return 10.0 * ca.sumsqr(obs[8:10])


def reacher(**make: Any) -> Task:
    """Reacher-v5 (obs ``[cos q (2), sin q (2), target (2), qvel (2), fingertip - target
    (x, y)]``, 10 values): the reward's distance and effort terms; a terminal cost on the
    distance."""
    return Task("reacher", "Reacher-v5", make, _reacher_cost, _reacher_terminal)


# ---- InvertedPendulum-v5
def _pendulum_cost(obs, a):
    """InvertedPendulum-v5 (obs ``[x, theta, x_dot, theta_dot]``): the reward is 1 per step
    alive; the cost keeps the pole up and the cart near 0, minus that alive bonus."""
    return (10.0 * obs[1] ** 2 + 0.1 * obs[0] ** 2 + 0.01 * obs[2] ** 2 + 0.1 * obs[3] ** 2
            + 0.001 * ca.sumsqr(a) - 1.0)


def _pendulum_terminated(obs: np.ndarray) -> np.ndarray:
    """The env terminates when ``|theta| > 0.2``."""
    return np.abs(obs[..., 1]) > 0.2


def inverted_pendulum(**make: Any) -> Task:
    """InvertedPendulum-v5: a regulator cost minus the alive bonus, the env's termination."""
    return Task("inverted-pendulum", "InvertedPendulum-v5", make, _pendulum_cost,
                termination_fn=_pendulum_terminated)


# ---- InvertedDoublePendulum-v5
def _tip(obs) -> tuple[Any, Any]:
    """Tip position ``(x, y)`` from obs ``[x_cart, sin q1, sin q2, cos q1, cos q2, ...]``
    (links of 0.6 m; ``cos(q1 + q2) = c1 c2 - s1 s2``)."""
    s1, s2, c1, c2 = obs[1], obs[2], obs[3], obs[4]
    return (obs[0] + 0.6 * s1 + 0.6 * (s1 * c2 + c1 * s2),
            0.6 * c1 + 0.6 * (c1 * c2 - s1 * s2))


def _double_pendulum_cost(obs, a):
    """InvertedDoublePendulum-v5: ``0.01 x_tip^2 + (y_tip - 2)^2 + 1e-3 v1^2 + 5e-3 v2^2``
    minus the alive bonus of 10 (the env's reward terms; velocities ``obs[6:8]``)."""
    x, y = _tip(obs)
    return 0.01 * x**2 + (y - 2.0) ** 2 + 1e-3 * obs[6] ** 2 + 5e-3 * obs[7] ** 2 - 10.0


def _double_pendulum_terminated(obs: np.ndarray) -> np.ndarray:
    """The env terminates when the tip's height ``y <= 1``."""
    _, y = _tip(np.moveaxis(np.asarray(obs, dtype=float), -1, 0))
    return y <= 1.0


def _double_pendulum_state(obs: np.ndarray) -> np.ndarray:
    """Model state ``[x, q1, q2, x', q1', q2']``: the angles from their sines and cosines
    (``atan2``; the env terminates long before a pole wraps at +-pi), the velocities, and not
    the observation's last entry (the slider's constraint force, which jumps at the rail's end)."""
    o = np.asarray(obs, dtype=float)
    return np.concatenate([o[..., :1], np.arctan2(o[..., 1:3], o[..., 3:5]), o[..., 5:8]],
                          axis=-1)


def _double_pendulum_obs(s, obs_ref):
    """The observation of model state ``s`` (CasADi); the constraint force from ``obs_ref``."""
    return ca.vertcat(s[0], ca.sin(s[1]), ca.sin(s[2]), ca.cos(s[1]), ca.cos(s[2]),
                      s[3], s[4], s[5], obs_ref[8])


def inverted_double_pendulum(**make: Any) -> Task:
    """InvertedDoublePendulum-v5: its reward terms minus the alive bonus, its termination, and
    a model state of joint angles and velocities (6 numbers, not the 9 of the observation: on
    the same 1,746 transitions the held-out one-step error fell from 0.16 to 0.13 of the step
    and the learned-model MPC held the poles 1.3-8x longer per episode,
    ``docs/results/idp_state_and_horizon.json``)."""
    return Task("inverted-double-pendulum", "InvertedDoublePendulum-v5", make,
                _double_pendulum_cost, termination_fn=_double_pendulum_terminated,
                state_fn=_double_pendulum_state, obs_fn=_double_pendulum_obs)


# ---- Pusher-v5
def _pusher_cost(obs, a):
    """Pusher-v5 (obs ``[qpos (7), qvel (7), fingertip, object, goal]``):
    ``0.5 |fingertip - object| + |object - goal| + 0.1 |a|^2``."""
    tip, obj, goal = obs[14:17], obs[17:20], obs[20:23]
    return 0.5 * _smooth_norm(tip - obj) + _smooth_norm(obj - goal) + 0.1 * ca.sumsqr(a)


def pusher(**make: Any) -> Task:
    """Pusher-v5: the reward's three terms (PETS' manipulation task)."""
    return Task("pusher", "Pusher-v5", make, _pusher_cost)


# ---- HalfCheetah-v5
def _cheetah_cost(obs, a):
    """HalfCheetah-v5 (obs ``[qpos[1:] (8), qvel (9)]``): ``-x_velocity + 0.1 |a|^2`` with the
    root's forward velocity ``obs[8]`` (the reward differences the position over the step; the
    observation holds the velocity at its end)."""
    return -obs[8] + 0.1 * ca.sumsqr(a)


def half_cheetah(**make: Any) -> Task:
    """HalfCheetah-v5: forward velocity minus the control cost (PETS' and MBPO's locomotion)."""
    return Task("half-cheetah", "HalfCheetah-v5", make, _cheetah_cost)


# ---- the project's arm
def two_link_arm(**make: Any) -> Task:
    """``mbtsr/TwoLinkArm-v0``: the env states its own quadratic cost (``cost_Q``, ``cost_R``)."""
    return Task("two-link-arm", "mbtsr/TwoLinkArm-v0", make)


#: the tasks by name
TASKS: dict[str, Callable[..., Task]] = {
    "reacher": reacher,
    "inverted-pendulum": inverted_pendulum,
    "inverted-double-pendulum": inverted_double_pendulum,
    "pusher": pusher,
    "half-cheetah": half_cheetah,
    "two-link-arm": two_link_arm,
}


def make_task(name: str, **make: Any) -> Task:
    """The task called ``name`` (a key of :data:`TASKS`) with env keywords ``make``."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; known: {sorted(TASKS)}")
    return TASKS[name](**make)

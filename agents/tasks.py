"""Reusable task definitions (:class:`Task`, the registry :data:`TASKS`, the benchmark suite's
:data:`SUITE`) and how the agent sees a task (:class:`EnvSpec`, :class:`StateMap`,
:class:`ObservationCost`); the task's functions are documented in docs/agent.md ("The cost: a
registry task, a learned reward, or yours").

Conventions of the tasks here: ``cost_fn(obs, action)`` is the env's NEGATED per-step reward on
the observation after the step (the closest equivalent where the reward uses another quantity,
said so); envs with an alive bonus subtract it, so that staying alive is cheaper than ending;
``termination_fn`` is numpy, batched ``obs [..., obs_dim] -> bool [...]``, the env's own rule;
norms are smoothed (``sqrt(|v|^2 + 1e-4)``). A task function takes the env's constructor
keywords (``inverted_pendulum(max_episode_steps=200)``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import casadi as ca
import numpy as np

from mbtsr.validation import as_array, call_user_fn, check_callable, check_int

if TYPE_CHECKING:
    import gymnasium as gym

__all__ = [
    "EnvSpec",
    "ObservationCost",
    "QuadraticTargetCost",
    "StateMap",
    "SUITE",
    "angle_pairs",
    "Task",
    "TASKS",
    "default_task_for_env",
    "env_spec",
    "half_cheetah",
    "inverted_double_pendulum",
    "inverted_pendulum",
    "make_task",
    "pusher",
    "reacher",
    "two_link_arm",
]


#: the task functions, by their argument names (:class:`agents.JacPropAgent`'s)
FUNCTION_NAMES = ("cost_fn", "terminal_cost_fn", "termination_fn", "state_fn", "obs_fn")


@dataclass(frozen=True)
class Task:
    """A control task on a Gymnasium env.

    :param name: short name (``"pusher"``).
    :param env_id: the registered Gymnasium id (``"Pusher-v5"``).
    :param make_kwargs: keyword arguments of ``gymnasium.make``.
    :param cost_fn: ``(obs, action) -> scalar`` (CasADi), or ``None`` (the env's own cost).
    :param terminal_cost_fn: ``obs -> scalar`` (CasADi), or ``None``.
    :param termination_fn: ``obs [..., obs_dim] -> bool [...]`` (numpy), or ``None``.
    :param state_fn: ``obs [..., obs_dim] -> state [..., n]`` (numpy), or ``None``.
    :param obs_fn: ``(state [n], obs_ref [obs_dim]) -> obs`` (CasADi), or ``None``; the five
        functions are :class:`agents.JacPropAgent`'s arguments of the same names.
    :param budget: a task of the benchmark suite (:data:`SUITE`): the env steps a learner gets.
    :param eval_every: a suite task: the env steps between evaluations.
    :param settings: a suite task: the agent settings it runs with (dotted ``AgentConfig``
        fields).
    """

    name: str
    env_id: str
    make_kwargs: dict[str, Any] = field(default_factory=dict)
    cost_fn: Callable[[Any, Any], Any] | None = None
    terminal_cost_fn: Callable[[Any], Any] | None = None
    termination_fn: Callable[[np.ndarray], np.ndarray] | None = None
    state_fn: Callable[[np.ndarray], np.ndarray] | None = None
    obs_fn: Callable[[Any, Any], Any] | None = None
    budget: int | None = None
    eval_every: int | None = None
    settings: dict[str, Any] = field(default_factory=dict)

    def make_env(self, **overrides: Any):
        """``gymnasium.make(env_id, **make_kwargs, **overrides)`` (:func:`gym_make`)."""
        return gym_make(self.env_id, **{**self.make_kwargs, **overrides})

    def agent_kwargs(self) -> dict[str, Any]:
        """The task's functions as keyword arguments of :class:`agents.JacPropAgent` (and of
        :func:`agents.evaluation.oracle_policy`)."""
        return {k: getattr(self, k) for k in FUNCTION_NAMES}


def gym_make(env_id: str, **kwargs: Any) -> gym.Env:
    """``gymnasium.make(env_id, **kwargs)``, the project's ``mbtsr/`` ids registered first."""
    import gymnasium as gym

    if env_id.startswith("mbtsr/"):
        import envs  # noqa: F401  (registers the mbtsr/ ids)
    return gym.make(env_id, **kwargs)


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


def inverted_double_pendulum(**make: Any) -> Task:
    """InvertedDoublePendulum-v5: its reward terms minus the alive bonus, its termination. The
    model state holds the joint angles, not their sines and cosines (the agent's rule,
    :func:`angle_pairs`; docs/notes/inverted_double_pendulum.md)."""
    return Task("inverted-double-pendulum", "InvertedDoublePendulum-v5", make,
                _double_pendulum_cost, termination_fn=_double_pendulum_terminated)


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


def _suite(task: Task, budget: int, eval_every: int, name: str | None = None,
           **settings: Any) -> tuple[str, Task]:
    return name or task.name, dataclasses.replace(task, budget=budget, eval_every=eval_every,
                                                  settings=settings)


#: the benchmark suite's tasks by suite name: registry tasks (their ``name`` is the registry's)
#: with the suite's env keywords, budget in env steps, evaluation period and agent settings
SUITE: dict[str, Task] = dict([
    _suite(two_link_arm(target_limit=0.85 * math.pi), 800, 200, "arm-far"),
    # each plan runs open loop for 10 steps
    _suite(two_link_arm(), 800, 200, "arm-open-loop", **{"planner.replan_every": 10}),
    _suite(reacher(), 2000, 250),
    _suite(inverted_pendulum(max_episode_steps=200), 2000, 250),
    _suite(inverted_double_pendulum(), 5000, 1000),
    _suite(pusher(), 3000, 300),
    _suite(half_cheetah(), 10000, 5000),
])


# ---- how the agent sees a task

@dataclass(frozen=True)
class EnvSpec:
    """Sizes and bounds of a Box-space env, as the agent needs them."""

    obs_dim: int
    act_dim: int
    u_min: np.ndarray
    u_max: np.ndarray
    episode_steps: int
    dt: float | None

    def to_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)} | {
            "u_min": self.u_min.tolist(), "u_max": self.u_max.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EnvSpec:
        u_min, u_max = (np.asarray(d[k], dtype=float) for k in ("u_min", "u_max"))
        return cls(int(d["obs_dim"]), int(d["act_dim"]), u_min, u_max, int(d["episode_steps"]),
                   None if d.get("dt") is None else float(d["dt"]))


def env_spec(env: gym.Env, episode_steps: int | None = None) -> EnvSpec:
    """Check that ``env`` has 1-D Box observation and action spaces with a bounded action space
    and a known episode length, and return its :class:`EnvSpec`.

    :param episode_steps: overrides the env's ``TimeLimit`` (``env.spec.max_episode_steps``,
        else ``env.unwrapped.episode_steps``).
    """
    import gymnasium as gym

    if not isinstance(env, gym.Env):
        raise TypeError(f"env must be a gymnasium.Env (one env, as gym.make returns; not a "
                        f"VecEnv), got {type(env).__name__}")
    obs_space, act_space = env.observation_space, env.action_space
    for name, space in (("observation_space", obs_space), ("action_space", act_space)):
        if not isinstance(space, gym.spaces.Box):
            raise ValueError(
                f"env.{name} must be a gymnasium.spaces.Box (continuous), got "
                f"{type(space).__name__}; the agent plans with gradients and needs continuous "
                "observations and actions"
            )
        if len(space.shape) != 1:
            raise ValueError(f"env.{name} must be 1-D, got shape {space.shape}")
    u_min = np.asarray(act_space.low, dtype=float)
    u_max = np.asarray(act_space.high, dtype=float)
    if not (np.all(np.isfinite(u_min)) and np.all(np.isfinite(u_max))):
        raise ValueError(
            f"env.action_space must be bounded (finite low/high) for the excitation signal and "
            f"the planner's box constraints, got low={u_min}, high={u_max}"
        )
    if np.any(u_max <= u_min):
        raise ValueError(f"env.action_space needs high > low, got low={u_min}, high={u_max}")
    if episode_steps is None:
        episode_steps = getattr(getattr(env, "spec", None), "max_episode_steps", None)
        if episode_steps is None:  # envs that truncate themselves (mbtsr/TwoLinkArm-v0)
            episode_steps = getattr(env.unwrapped, "episode_steps", None)
        if episode_steps is None:
            raise ValueError(
                "the env has no TimeLimit (env.spec.max_episode_steps is None) and no "
                "env.unwrapped.episode_steps; set AgentConfig.collection.episode_steps"
            )
    check_int("episode_steps", episode_steps, 1)
    dt = getattr(env.unwrapped, "dt", None)
    return EnvSpec(int(obs_space.shape[0]), int(act_space.shape[0]), u_min, u_max,
                   int(episode_steps), None if dt is None else float(dt))


class StateMap:
    """Observation <-> model-state maps.

    :param state_fn: ``obs [..., obs_dim] -> state [..., n]`` (numpy). ``None``: identity.
    :param obs_fn: ``(state [n], obs_ref [obs_dim]) -> obs [obs_dim]`` (CasADi); ``None``: identity.
    :param prefix: serialisable shortcut: the state is ``obs[:prefix]`` and
        ``obs_fn(s, ref) = [s; ref[prefix:]]`` (the two-link arm's).
    :param angles: serialisable shortcut: ``(i, j)`` column pairs holding the sine and cosine of
        one angle (:func:`angle_pairs`); the state is the observation with ``obs[i]`` replaced by
        ``atan2(obs[i], obs[j])`` and ``obs[j]`` left out.
    """

    def __init__(
        self,
        state_fn: Callable[[np.ndarray], np.ndarray] | None = None,
        obs_fn: Callable[[Any, Any], Any] | None = None,
        *,
        prefix: int | None = None,
        angles: tuple[tuple[int, int], ...] = (),
    ) -> None:
        if prefix is not None or angles:
            if state_fn is not None or obs_fn is not None or (prefix is not None and angles):
                raise ValueError("give one of prefix, angles or state_fn/obs_fn")
            if prefix is not None and int(prefix) < 1:
                raise ValueError(f"prefix must be >= 1, got {prefix}")
        elif state_fn is None and obs_fn is not None:
            raise ValueError("obs_fn was given without state_fn; give both or neither")
        elif state_fn is not None and obs_fn is None:
            raise ValueError(
                "state_fn was given without obs_fn: the cost is defined on observations, so the "
                "planner needs obs_fn(state, obs_ref) to evaluate it on predicted states"
            )
        self.prefix = None if prefix is None else int(prefix)
        cols = [c for p in angles for c in p]
        if any(len(p) != 2 for p in angles) or len(set(cols)) < len(cols) or not all(
                isinstance(c, (int, np.integer)) and c >= 0 for c in cols):
            raise ValueError(f"angles must be (sine column, cosine column) pairs of distinct "
                             f"column indices >= 0, got {angles!r}")
        self.angles = tuple((int(i), int(j)) for i, j in angles)
        self._state_fn = state_fn
        self._obs_fn = obs_fn

    @property
    def serializable(self) -> bool:
        return self._state_fn is None

    @property
    def identity(self) -> bool:
        return self.serializable and self.prefix is None and not self.angles

    def to_dict(self) -> dict[str, Any]:
        if not self.serializable:
            raise ValueError("a StateMap with user functions cannot be serialised")
        return {"prefix": self.prefix, **({"angles": [list(p) for p in self.angles]}
                                          if self.angles else {})}  # as before angles existed

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StateMap:
        return cls(prefix=d.get("prefix"), angles=d.get("angles", ()))

    def state(self, obs: np.ndarray) -> np.ndarray:
        """``obs [..., obs_dim] -> state [..., n]`` as float64."""
        obs = np.asarray(obs, dtype=float)
        if self.prefix is not None:
            return obs[..., : self.prefix].copy()
        if self.angles:
            sin, cos = (list(c) for c in zip(*self.angles))
            s = obs.copy()
            s[..., sin] = np.arctan2(obs[..., sin], obs[..., cos])
            return np.delete(s, cos, axis=-1)
        if self._state_fn is None:
            return obs.copy()
        return np.asarray(self._state_fn(obs), dtype=float)

    def observation(self, state: Any, obs_ref: Any) -> Any:
        """``(state [n], obs_ref [obs_dim]) -> obs [obs_dim]`` (CasADi or numpy)."""
        if self.prefix is not None:
            return ca.vertcat(state, obs_ref[self.prefix :])
        if self.angles:
            sin_at, cos_at = dict(self.angles), {j: i for i, j in self.angles}
            at = {i: k for k, i in enumerate(i for i in range(obs_ref.shape[0])
                                             if i not in cos_at)}  # column -> state entry
            return ca.vertcat(*(ca.sin(state[at[i]]) if i in sin_at else ca.cos(
                state[at[cos_at[i]]]) if i in cos_at else state[at[i]]
                for i in range(obs_ref.shape[0])))
        if self._obs_fn is None:
            return state
        return self._obs_fn(state, obs_ref)


def angle_pairs(obs: np.ndarray, max_angle: float = math.pi / 2) -> tuple[tuple[int, int], ...]:
    """Column pairs ``(i, j)`` of observations ``obs [N, obs_dim]`` that hold one angle's sine
    and cosine (:class:`StateMap`'s ``angles``): ``obs_i^2 + obs_j^2 = 1`` (to 1e-6) on every
    row, both move, and ``atan2(obs_i, obs_j)`` stays within ``+-max_angle`` (away from +-pi)."""
    o = np.asarray(obs, dtype=float)
    sq, moves, pairs = o**2, np.ptp(o, axis=0) > 1e-6, []
    for i in np.flatnonzero(moves):
        for j in np.flatnonzero(moves & np.all(np.abs(sq[:, i:i + 1] + sq - 1) <= 1e-6, 0)):
            for a, b in ((int(i), int(j)), (int(j), int(i))):
                if not {a, b} & set(sum(pairs, ())) and np.all(
                        np.abs(np.arctan2(o[:, a], o[:, b])) <= max_angle):
                    pairs.append((a, b))
    return tuple(sorted(pairs))


class QuadraticTargetCost:
    """``c(obs, a) = (x - x_goal)^T Q (x - x_goal) + a^T R a``, ``x = obs[:n]``, ``x_goal =
    [obs[target_index], 0, ...]``: the two-link arm's cost (``reward = -c``). Serialisable.

    :param Q: ``[n, n]`` state weight. :param R: ``[m, m]`` action weight.
    :param target_index: observation indices holding the goal of the first ``len`` states.
    """

    def __init__(self, Q: np.ndarray, R: np.ndarray, target_index: list[int]) -> None:
        self.Q = as_array("Q", Q, ndim=2)
        self.R = as_array("R", R, ndim=2)
        n = self.Q.shape[0]
        as_array("Q", self.Q, (n, n))
        as_array("R", self.R, (self.R.shape[0], self.R.shape[0]))
        self.target_index = [int(i) for i in target_index]
        if len(self.target_index) > n:
            raise ValueError(f"target_index has {len(self.target_index)} entries for n={n}")
        self.n = n

    def __call__(self, obs: Any, a: Any) -> Any:
        x = obs[: self.n]
        goal = ca.vertcat(
            *[obs[i] for i in self.target_index], ca.DM.zeros(self.n - len(self.target_index))
        )
        e = x - goal
        return ca.bilin(ca.DM(self.Q), e, e) + ca.bilin(ca.DM(self.R), a, a)

    def to_dict(self) -> dict[str, Any]:
        return {"Q": self.Q.tolist(), "R": self.R.tolist(), "target_index": self.target_index}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> QuadraticTargetCost:
        return cls(np.asarray(d["Q"]), np.asarray(d["R"]), d["target_index"])


class ObservationCost:
    """The stage cost ``cost_fn(obs, a)`` compiled once to CasADi and composed with the state
    map: ``stage(state [n], a [m], obs_ref [obs_dim])`` for the planner, ``terminal``.

    :raises ValueError: if ``cost_fn`` or the map fail for these dimensions or the cost is not
        a scalar.
    """

    def __init__(
        self,
        cost_fn: Callable[[Any, Any], Any],
        state_map: StateMap,
        spec: EnvSpec,
        state_dim: int,
        terminal_cost_fn: Callable[[Any], Any] | None = None,
    ) -> None:
        self.cost_fn = check_callable("cost_fn", cost_fn, "(obs, action) -> cost")
        self.state_map = state_map
        self.spec = spec
        self.state_dim = state_dim
        o = ca.SX.sym("obs", spec.obs_dim)
        a = ca.SX.sym("a", spec.act_dim)
        s = ca.SX.sym("s", state_dim)
        c_obs = _scalar(
            "cost_fn", cost_fn, o, a,
            failure=f"cost_fn(obs, action) failed on a symbolic observation of dimension "
            f"{spec.obs_dim} and action of dimension {spec.act_dim} (does the cost match the "
            "env's spaces? it must be written with casadi operations)")
        if c_obs.is_constant():
            raise ValueError("cost_fn does not depend on the observation or the action")
        self.obs_function = ca.Function("cost_obs", [o, a], [c_obs])
        o_of_s = call_user_fn(
            lambda: ca.SX(state_map.observation(s, o)),
            failure=f"obs_fn failed on a symbolic state of dimension {state_dim} and an "
            f"observation of dimension {spec.obs_dim}",
        )
        if o_of_s.shape != (spec.obs_dim, 1):
            raise ValueError(
                f"obs_fn(state, obs_ref) must return an observation of shape ({spec.obs_dim},), "
                f"got {o_of_s.shape}"
            )
        c_state = ca.substitute(c_obs, o, o_of_s)
        # o: the reference observation, which supplies what the model does not predict
        self.stage = ca.Function("cost_state", [s, a, o], [c_state])
        # terminal cost: the user's terminal_cost_fn(obs), else the stage cost at zero action
        self.terminal_cost_fn = terminal_cost_fn
        if terminal_cost_fn is None:
            c_term = ca.substitute(c_state, a, ca.DM.zeros(spec.act_dim))
        else:
            check_callable("terminal_cost_fn", terminal_cost_fn, "obs -> cost")
            c_term_obs = _scalar(
                "terminal_cost_fn", terminal_cost_fn, o,
                failure=f"terminal_cost_fn(obs) failed on a symbolic observation of dimension "
                f"{spec.obs_dim} (write it with casadi operations)")
            c_term = ca.substitute(c_term_obs, o, o_of_s)
        self.terminal = ca.Function("cost_state_terminal", [s, o], [c_term])

    def on_observations(self, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """Per-step cost ``[T]`` of an episode: ``obs [T, obs_dim]``, ``actions [T, m]``."""
        obs = np.asarray(obs, dtype=float)
        actions = np.asarray(actions, dtype=float)
        T = actions.shape[0]
        return np.asarray(self.obs_function.map(T)(obs.T, actions.T)).reshape(T)


def _scalar(name: str, fn: Callable, *symbols: ca.SX, failure: str) -> ca.SX:
    """``fn(*symbols)``, a user's cost on CasADi symbols, as a scalar expression; an error names
    ``name`` (``failure``: the message when ``fn`` raises)."""
    c = call_user_fn(fn, *symbols, failure=failure)
    try:
        c = ca.SX(c)
    except Exception:
        raise ValueError(f"{name} must return a casadi scalar expression, got "
                         f"{type(c).__name__}") from None
    if c.shape != (1, 1):
        raise ValueError(f"{name} must return a scalar, got shape {c.shape}")
    return c


def default_task_for_env(env: gym.Env) -> tuple[QuadraticTargetCost, StateMap] | None:
    """The built-in cost and state map for envs that describe their own quadratic cost
    (``env.unwrapped.cost_Q``, ``cost_R`` and ``target_index``/a 2-D ``target`` in the
    observation after the state, as ``mbtsr/TwoLinkArm-v0`` does); ``None`` otherwise."""
    u = env.unwrapped
    Q, R = getattr(u, "cost_Q", None), getattr(u, "cost_R", None)
    if Q is None or R is None:
        return None
    Q = np.asarray(Q, dtype=float)
    n = Q.shape[0]
    obs_dim = env.observation_space.shape[0]
    target_index = list(range(n, obs_dim))
    return QuadraticTargetCost(Q, np.asarray(R, dtype=float), target_index), StateMap(prefix=n)

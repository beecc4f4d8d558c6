"""How the agent sees an environment: spaces, the model state, and the cost.

The user describes the control task on the env's own terms:

* ``cost_fn(obs, action) -> scalar``: a CasADi-compatible stage cost on an observation
  ``obs: [obs_dim]`` and an action ``action: [act_dim]`` (env units). It is called once with
  CasADi ``SX`` column vectors to build the planner's cost, so write it with ``casadi``
  operations (``obs[0]``, ``ca.sumsqr``, ``ca.cos``, ``ca.mtimes`` ...).
* optionally ``terminal_cost_fn(obs) -> scalar`` (CasADi-compatible): the cost of the last
  predicted observation of a plan (default: the stage cost at zero action), scaled by
  ``AgentConfig.planner.terminal_weight``.
* optionally ``state_fn(obs) -> state`` (numpy) and ``obs_fn(state, obs_ref) -> obs``
  (CasADi-compatible): the model learns the dynamics of ``state``, and the cost of a predicted
  state is ``cost_fn(obs_fn(state, obs_ref), action)``, where ``obs_ref`` is the current real
  observation (it supplies parts of the observation the model does not predict, such as a
  target). Without them the model state is the observation itself.
  **Contract:** ``state_fn`` is applied to whole episodes, so it must map a batch
  ``obs [B, obs_dim] -> state [B, n]`` row by row as well as one ``obs [obs_dim] -> [n]``
  (write it with ``obs[..., i]``); ``obs_fn`` is called once on CasADi symbols
  ``state [n]``, ``obs_ref [obs_dim]`` and must return ``[obs_dim]``. Both are checked at
  construction (on one observation and on a batch of three).
* optionally ``termination_fn(obs) -> bool`` (numpy, batched ``[..., obs_dim] -> [...]``):
  predicted observations where the env would terminate; the planner (iLQR's line search, CEM's
  ranking) stops accumulating cost after a predicted termination (as PETS does), see
  :func:`mbtsr.costs.truncated_total`.

Everything is checked at construction: non-Box spaces, unbounded actions, a cost that fails on
or does not return a scalar for the given dimensions, maps that return the wrong sizes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import casadi as ca
import gymnasium as gym
import numpy as np

from mbtsr.validation import as_array, call_user_fn, check_callable

__all__ = [
    "EnvSpec",
    "StateMap",
    "ObservationCost",
    "QuadraticTargetCost",
    "env_spec",
    "default_task_for_env",
]


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
        return {
            "obs_dim": self.obs_dim,
            "act_dim": self.act_dim,
            "u_min": self.u_min.tolist(),
            "u_max": self.u_max.tolist(),
            "episode_steps": self.episode_steps,
            "dt": self.dt,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EnvSpec:
        return cls(
            int(d["obs_dim"]),
            int(d["act_dim"]),
            np.asarray(d["u_min"], dtype=float),
            np.asarray(d["u_max"], dtype=float),
            int(d["episode_steps"]),
            None if d.get("dt") is None else float(d["dt"]),
        )


def env_spec(env: gym.Env, episode_steps: int | None = None) -> EnvSpec:
    """Check that ``env`` has 1-D Box observation and action spaces with a bounded action space
    and a known episode length, and return its :class:`EnvSpec`.

    :param episode_steps: overrides the env's ``TimeLimit`` (``env.spec.max_episode_steps``,
        else ``env.unwrapped.episode_steps``).
    """
    if not isinstance(env, gym.Env):
        raise TypeError(f"env must be a gymnasium.Env, got {type(env).__name__}")
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
        spec = getattr(env, "spec", None)
        episode_steps = getattr(spec, "max_episode_steps", None) if spec is not None else None
        if episode_steps is None:  # envs that truncate themselves (mbtsr/TwoLinkArm-v0)
            episode_steps = getattr(env.unwrapped, "episode_steps", None)
        if episode_steps is None:
            raise ValueError(
                "the env has no TimeLimit (env.spec.max_episode_steps is None) and no "
                "env.unwrapped.episode_steps; set AgentConfig.collection.episode_steps"
            )
    if isinstance(episode_steps, bool) or int(episode_steps) != episode_steps \
            or episode_steps < 1:
        raise ValueError(f"episode_steps must be an integer >= 1, got {episode_steps!r}")
    dt = getattr(env.unwrapped, "dt", None)
    return EnvSpec(
        obs_dim=int(obs_space.shape[0]),
        act_dim=int(act_space.shape[0]),
        u_min=u_min,
        u_max=u_max,
        episode_steps=int(episode_steps),
        dt=None if dt is None else float(dt),
    )


class StateMap:
    """Observation <-> model-state maps.

    :param state_fn: ``obs [..., obs_dim] -> state [..., n]`` (numpy). ``None``: identity.
    :param obs_fn: ``(state [n], obs_ref [obs_dim]) -> obs [obs_dim]`` (CasADi-compatible).
        ``None``: identity (requires ``state_fn is None``).
    :param prefix: serialisable shortcut: the state is ``obs[:prefix]`` and
        ``obs_fn(s, ref) = [s; ref[prefix:]]`` (used for the two-link arm, whose observation is
        ``[x (4), target (2)]``).
    """

    def __init__(
        self,
        state_fn: Callable[[np.ndarray], np.ndarray] | None = None,
        obs_fn: Callable[[Any, Any], Any] | None = None,
        *,
        prefix: int | None = None,
    ) -> None:
        if prefix is not None:
            if state_fn is not None or obs_fn is not None:
                raise ValueError("give either prefix or state_fn/obs_fn, not both")
            if int(prefix) < 1:
                raise ValueError(f"prefix must be >= 1, got {prefix}")
        elif state_fn is None and obs_fn is not None:
            raise ValueError("obs_fn was given without state_fn; give both or neither")
        elif state_fn is not None and obs_fn is None:
            raise ValueError(
                "state_fn was given without obs_fn: the cost is defined on observations, so the "
                "planner needs obs_fn(state, obs_ref) to evaluate it on predicted states"
            )
        self.prefix = None if prefix is None else int(prefix)
        self._state_fn = state_fn
        self._obs_fn = obs_fn

    @property
    def serializable(self) -> bool:
        return self._state_fn is None

    def to_dict(self) -> dict[str, Any]:
        if not self.serializable:
            raise ValueError("a StateMap with user functions cannot be serialised")
        return {"prefix": self.prefix}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> StateMap:
        return cls(prefix=d.get("prefix"))

    def state(self, obs: np.ndarray) -> np.ndarray:
        """``obs [..., obs_dim] -> state [..., n]`` as float64."""
        obs = np.asarray(obs, dtype=float)
        if self.prefix is not None:
            return obs[..., : self.prefix].copy()
        if self._state_fn is None:
            return obs.copy()
        return np.asarray(self._state_fn(obs), dtype=float)

    def observation(self, state: Any, obs_ref: Any) -> Any:
        """``(state [n], obs_ref [obs_dim]) -> obs [obs_dim]`` (CasADi or numpy)."""
        if self.prefix is not None:
            return ca.vertcat(state, obs_ref[self.prefix :])
        if self._obs_fn is None:
            return state
        return self._obs_fn(state, obs_ref)


class QuadraticTargetCost:
    """``c(obs, a) = (x - x_goal)^T Q (x - x_goal) + a^T R a`` with ``x = obs[:n]`` and
    ``x_goal = [obs[target_index], 0, ...]`` (goal positions from the observation, zero
    velocities) -- the two-link arm's cost (``reward = -c``). Serialisable.

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
    """The stage cost ``cost_fn(obs, a)`` compiled to CasADi and composed with the state map.

    Built once; ``stage`` is a ``casadi.Function`` ``(state [n], a [m], obs_ref [obs_dim]) ->
    cost`` used by the planner, ``on_observations`` evaluates the cost of a real episode.

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
        c_obs = _call_cost(cost_fn, o, a, spec)
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
        # p: the reference observation, which supplies what the model does not predict
        p = o
        self.stage = ca.Function("cost_state", [s, a, p], [c_state])
        # terminal cost: the user's terminal_cost_fn(obs), else the stage cost at zero action
        self.terminal_cost_fn = terminal_cost_fn
        if terminal_cost_fn is None:
            c_term = ca.substitute(c_state, a, ca.DM.zeros(spec.act_dim))
        else:
            check_callable("terminal_cost_fn", terminal_cost_fn, "obs -> cost")
            c_term_obs = call_user_fn(
                lambda: ca.SX(terminal_cost_fn(o)),
                failure=f"terminal_cost_fn(obs) failed on a symbolic observation of dimension "
                f"{spec.obs_dim} (write it with casadi operations)",
            )
            if c_term_obs.shape != (1, 1):
                raise ValueError(
                    f"terminal_cost_fn must return a scalar, got shape {c_term_obs.shape}")
            c_term = ca.substitute(c_term_obs, o, o_of_s)
        self.terminal = ca.Function("cost_state_terminal", [s, p], [c_term])

    def on_observations(self, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """Per-step cost of a recorded episode: ``obs: [T, obs_dim]``, ``actions: [T, m]``
        -> ``[T]``."""
        obs = np.asarray(obs, dtype=float)
        actions = np.asarray(actions, dtype=float)
        T = actions.shape[0]
        return np.asarray(self.obs_function.map(T)(obs.T, actions.T)).reshape(T)


def _call_cost(cost_fn: Callable, o: ca.SX, a: ca.SX, spec: EnvSpec) -> ca.SX:
    c = call_user_fn(
        cost_fn, o, a,
        failure=f"cost_fn(obs, action) failed on a symbolic observation of dimension "
        f"{spec.obs_dim} and action of dimension {spec.act_dim} (does the cost match the env's "
        f"spaces? it must be written with casadi operations)",
    )
    try:
        c = ca.SX(c)
    except Exception:
        raise ValueError(
            f"cost_fn must return a casadi scalar expression, got {type(c).__name__}"
        ) from None
    if c.shape != (1, 1):
        raise ValueError(f"cost_fn must return a scalar, got shape {c.shape}")
    if c.is_constant():
        raise ValueError("cost_fn does not depend on the observation or the action")
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

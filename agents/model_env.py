"""The learned dynamics model as a Gymnasium environment (mbrl-lib's ``ModelEnv``, MBPO's pattern):
a model-free learner (SB3 SAC, PPO, ...) trains inside the frozen model instead of the real env.

What each argument does (starts, member sampling, reward, termination): docs/agent.md, section
"The learned model as a Gymnasium env". The env never trains or changes the model; every
random draw comes from ``self.np_random``, seeded by ``reset(seed=...)``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from agents.tasks import StateMap
from mbtsr.validation import as_array, check_callable, check_choice, check_int

__all__ = ["ModelEnv"]

MEMBER_MODES = ("mean", "step", "episode")


class ModelEnv(gym.Env):
    """A Gymnasium env whose transitions come from a learned (frozen) dynamics model.

    :param model: ``state_dim``, ``action_dim``, batched ``step(x, u)``; ``member_predictions``
        for ``member != "mean"``.
    :param observation_space: 1-D ``Box`` of the real env (observations are cast to its dtype and
        clipped to its finite bounds).
    :param action_space: 1-D bounded ``Box`` of the real env (actions are clipped to it).
    :param cost_fn: ``(obs [obs_dim], action [m]) -> scalar`` (numpy in; a CasADi ``DM`` or a
        0-d/1-element array out is accepted).
    :param start_obs: ``[N, obs_dim]`` recorded start observations, drawn uniformly on reset.
    :param reset_fn: ``rng -> obs [obs_dim]``, called with ``self.np_random`` (give exactly one of
        ``start_obs`` and ``reset_fn``).
    :param state_fn: ``obs [obs_dim] -> state [n]``; default identity.
    :param obs_fn: ``(state [n], obs_ref [obs_dim]) -> obs [obs_dim]``; default identity. Give
        both maps or neither.
    :param termination_fn: ``(obs, action, next_obs) -> bool``; default: never terminates.
    :param member: ``"mean"`` (the ensemble mean), ``"step"`` (a random member every step) or
        ``"episode"`` (one random member per episode).
    :param cost_on: ``"next"`` (reward ``-cost_fn(next_obs, a)``) or ``"current"``.
    :param max_episode_steps: truncation length (>= 1), or ``None`` for no truncation.
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        model: Any,
        observation_space: gym.spaces.Box,
        action_space: gym.spaces.Box,
        cost_fn: Callable[[np.ndarray, np.ndarray], Any],
        *,
        start_obs: np.ndarray | None = None,
        reset_fn: Callable[[np.random.Generator], np.ndarray] | None = None,
        state_fn: Callable[[np.ndarray], np.ndarray] | None = None,
        obs_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
        termination_fn: Callable[[np.ndarray, np.ndarray, np.ndarray], bool] | None = None,
        member: str = "mean",
        cost_on: str = "next",
        max_episode_steps: int | None = None,
    ) -> None:
        super().__init__()
        for name in ("step", "state_dim", "action_dim"):
            if not hasattr(model, name):
                raise TypeError(f"model must have step(x, u), state_dim and action_dim; "
                                f"{type(model).__name__} has no {name!r}")
        for name, space in (("observation_space", observation_space),
                            ("action_space", action_space)):
            if not isinstance(space, gym.spaces.Box) or len(space.shape) != 1:
                raise ValueError(f"{name} must be a 1-D gymnasium.spaces.Box, got {space!r}")
        if not (np.all(np.isfinite(action_space.low)) and np.all(np.isfinite(action_space.high))):
            raise ValueError("action_space must be bounded (finite low and high)")
        check_choice("member", member, MEMBER_MODES)
        if member != "mean" and not hasattr(model, "member_predictions"):
            raise ValueError(
                f"member={member!r} samples ensemble members, but {type(model).__name__} has no "
                "member_predictions(x, u); use member='mean'"
            )
        check_choice("cost_on", cost_on, ("next", "current"))
        check_callable("cost_fn", cost_fn, "(obs, action) -> cost")
        if (start_obs is None) == (reset_fn is None):
            raise ValueError("give exactly one of start_obs and reset_fn")
        if max_episode_steps is not None:
            max_episode_steps = check_int("max_episode_steps", max_episode_steps, 1)
        self.model = model
        self.observation_space = observation_space
        self.action_space = action_space
        self.cost_fn = cost_fn
        self.reset_fn = reset_fn
        self.state_map = StateMap(state_fn, obs_fn)  # refuses one without the other
        self.termination_fn = termination_fn
        self.member = member
        self.cost_on = cost_on
        self.max_episode_steps = max_episode_steps
        self.obs_dim = int(observation_space.shape[0])
        self._u_low = np.asarray(action_space.low, dtype=np.float64)
        self._u_high = np.asarray(action_space.high, dtype=np.float64)
        if int(model.action_dim) != action_space.shape[0]:
            raise ValueError(f"model.action_dim = {model.action_dim} does not match action_space "
                             f"{action_space.shape}")
        self.start_obs = None if start_obs is None else as_array(
            "start_obs", start_obs, (None, self.obs_dim))
        if self.start_obs is not None and not len(self.start_obs):
            raise ValueError("start_obs must hold at least one observation, got shape [0, *]")
        probe = self.start_obs[0] if self.start_obs is not None else np.zeros(self.obs_dim)
        s = self._state(probe)
        if s.shape != (int(model.state_dim),):
            raise ValueError(
                f"state_fn(obs) gives a state of shape {list(s.shape)}, the model needs "
                f"[{model.state_dim}]"
            )
        self._obs: np.ndarray | None = None
        self._k: int | None = None
        self._t = 0

    # -------------------------------------------------------------- maps
    def _state(self, obs: np.ndarray) -> np.ndarray:
        return np.asarray(self.state_map.state(obs), dtype=np.float64).reshape(-1)

    def _observation(self, state: np.ndarray, obs_ref: np.ndarray) -> np.ndarray:
        o = np.asarray(self.state_map.observation(state, obs_ref), dtype=np.float64).reshape(-1)
        if o.shape != (self.obs_dim,):
            raise ValueError(f"obs_fn returned shape {list(o.shape)}, expected [{self.obs_dim}]")
        return o

    def _cost(self, obs: np.ndarray, action: np.ndarray) -> float:
        c = np.asarray(self.cost_fn(obs, action), dtype=np.float64)
        if c.size != 1:
            raise ValueError(f"cost_fn must return a scalar, got shape {list(c.shape)}")
        return float(c.reshape(()))

    def _emit(self, obs: np.ndarray) -> np.ndarray:
        """The observation as the space wants it: clipped to finite bounds, in its dtype."""
        sp = self.observation_space
        return np.clip(obs, sp.low, sp.high).astype(sp.dtype)

    def _predict(self, state: np.ndarray, action: np.ndarray) -> np.ndarray:
        if self.member == "mean":
            return np.asarray(self.model.step(state, action), dtype=np.float64)
        preds = np.asarray(self.model.member_predictions(state, action), dtype=np.float64)
        if self.member == "step" or self._k is None:
            k = int(self.np_random.integers(preds.shape[0]))
            if self.member == "episode":
                self._k = k
        return preds[k if self.member == "step" else self._k]

    # -------------------------------------------------------------- gymnasium API
    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[np.ndarray, dict]:
        """Start an episode at ``options["obs"]``, a recorded start or ``reset_fn``'s draw."""
        super().reset(seed=seed)
        if options is not None and "obs" in options:
            obs = np.asarray(options["obs"], dtype=np.float64).reshape(-1)
        elif self.start_obs is not None:
            obs = self.start_obs[int(self.np_random.integers(self.start_obs.shape[0]))].copy()
        else:
            obs = np.asarray(self.reset_fn(self.np_random), dtype=np.float64).reshape(-1)
        if obs.shape != (self.obs_dim,) or not np.isfinite(obs).all():
            raise ValueError(f"the start observation must be finite [{self.obs_dim}], got {obs}")
        self._k = None  # "episode": drawn at the first step, when the ensemble size is known
        self._obs = self._emit(obs).astype(np.float64)
        self._t = 0
        return self._emit(self._obs), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != self._u_low.shape or not np.isfinite(a).all():
            raise ValueError(
                f"action must be a finite array of shape {list(self._u_low.shape)}, got {action!r}"
            )
        a = np.clip(a, self._u_low, self._u_high)
        obs = self._obs
        next_state = self._predict(self._state(obs), a)
        info: dict[str, Any] = {"model_diverged": False}
        if self.member == "episode":
            info["member"] = self._k
        if not np.isfinite(next_state).all():
            next_obs, terminated = obs, True
            info["model_diverged"] = True
        else:
            next_obs = self._emit(self._observation(next_state, obs)).astype(np.float64)
            done = self.termination_fn
            terminated = bool(done(obs, a, next_obs)) if done is not None else False
        reward = -self._cost(next_obs if self.cost_on == "next" else obs, a)
        self._obs = next_obs
        self._t += 1
        truncated = self.max_episode_steps is not None and self._t >= self.max_episode_steps
        return self._emit(next_obs), reward, terminated, bool(truncated and not terminated), info

    # -------------------------------------------------------------- construction from an agent
    @classmethod
    def from_agent(
        cls,
        agent: Any,
        *,
        start_obs: np.ndarray | None = None,
        reset_fn: Callable[[np.random.Generator], np.ndarray] | None = None,
        termination_fn: Callable[[np.ndarray, np.ndarray, np.ndarray], bool] | None = None,
        member: str = "mean",
    ) -> ModelEnv:
        """The model of a :class:`agents.jacprop_agent.JacPropAgent` with its task's cost and
        state map, its env's spaces and episode length, and the task's ``termination_fn`` (the
        agent's ``obs -> bool``, applied to the next observation) unless one is given.

        Without ``start_obs``/``reset_fn`` the start observations come from the real env's own
        reset distribution (``agent.env.reset(seed=...)`` with a seed drawn from the ModelEnv's
        generator; no real step is taken).
        """
        env = agent.env
        if env is None and start_obs is None and reset_fn is None:
            raise ValueError("the agent has no env: pass start_obs or reset_fn")
        if start_obs is None and reset_fn is None:
            def reset_fn(rng: np.random.Generator) -> np.ndarray:
                return env.reset(seed=int(rng.integers(2**31 - 1)))[0]
        spec = agent.spec
        if env is not None:
            obs_space, act_space = env.observation_space, env.action_space
        else:  # an act-only agent: the spaces of its saved spec
            obs_space = gym.spaces.Box(-np.inf, np.inf, (spec.obs_dim,), np.float64)
            act_space = gym.spaces.Box(spec.u_min.astype(np.float32), spec.u_max.astype(np.float32))
        task_done = getattr(agent, "termination_fn", None)  # obs [..., obs_dim] -> bool [...]
        if termination_fn is None and task_done is not None:
            def termination_fn(obs, action, next_obs):
                return bool(np.asarray(task_done(next_obs)).reshape(()))
        frozen = agent.model.freeze() if hasattr(agent.model, "freeze") else agent.model
        state_map = agent.state_map
        cost_on = "next"
        if agent.cost_fn is None:  # a learned reward: r_hat(s_t, a_t), on the step's start
            reward, cost_on = agent.task_cost.frozen(), "current"

            def cost(o: np.ndarray, a: np.ndarray) -> np.ndarray:
                return -reward.predict(state_map.state(o), np.asarray(a, dtype=float))
        else:
            cost = agent.task_cost.obs_function  # casadi Function (obs, a) -> cost
        return cls(
            frozen,
            obs_space,
            act_space,
            lambda o, a: cost(o, a),
            start_obs=start_obs,
            reset_fn=reset_fn,
            state_fn=state_map.state,
            obs_fn=lambda s, o: np.asarray(state_map.observation(s, o), dtype=np.float64),
            termination_fn=termination_fn,
            member=member,
            max_episode_steps=spec.episode_steps,
            cost_on=cost_on,
        )

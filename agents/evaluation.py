"""Evaluation protocol: fixed episodes, episode cost ``-sum(rewards)``, the true-model oracle and
the agent's :class:`Evaluator` (docs/agent.md, "Evaluation, the oracle, "solved""). Episode ``i``
is reset with ``seed + i`` and ``options={"target": targets[i]}``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

import mbtsr
from agents.checkpoint import atomic_write_text, env_fingerprint
from agents.config import AgentConfig, PlannerConfig
from agents.planning import ReplanEvery, make_policy
from agents.tasks import (
    ObservationCost,
    QuadraticTargetCost,
    StateMap,
    default_task_for_env,
    env_spec,
    gym_make,
)
from mbtsr.episode import EpisodeRecord, as_policy, run_episode
from mbtsr.ilqr import ILQROptions
from mbtsr.io import json_default
from mbtsr.validation import check_int

__all__ = [
    "NOT_EVALUATED",
    "EpisodeRecord",
    "Evaluator",
    "make_env",
    "run_episode",
    "evaluation_targets",
    "evaluate_policy_costs",
    "evaluate_policy_cost",
    "oracle_policy",
    "has_true_model",
    "cached_costs",
    "oracle_cache_key",
    "physics_fingerprint",
    "solved_threshold",
]


#: the evaluation fields of an episode's log row without an evaluation
NOT_EVALUATED: dict[str, Any] = {
    "eval_cost": None, "eval_return": None, "eval_returns": None, "oracle_cost": None,
    "cost_ratio": None, "eval_episodes_run": 0, "solved": False}


def make_env(env: gym.Env | str, **kwargs: Any) -> tuple[gym.Env, bool]:
    """``(env, created)``: ``env`` itself, or :func:`agents.tasks.gym_make` ``(env, **kwargs)``."""
    if isinstance(env, gym.Env):
        return env, False
    if not isinstance(env, str):
        raise TypeError(f"env must be a gymnasium.Env or an env id string, got {env!r}")
    return gym_make(env, **kwargs), True


def evaluation_targets(
    n: int = 10, seed: int = 0, env_id: str | gym.Env | None = None
) -> list[np.ndarray]:
    """``n`` targets drawn by the env's own target distribution: ``info["target"]`` after
    ``reset(seed=seed + i)``.

    :param n: number of targets (>= 1).
    :param seed: base seed (>= 0).
    :param env_id: an env id or instance that reports ``info["target"]`` (``None``: the arm).
    """
    if env_id is None:
        from envs import ARM_ID  # here, not at import: importing envs sets MUJOCO_GL

        env_id = ARM_ID
    check_int("n", n, 1)
    check_int("seed", seed, 0)
    env, created = make_env(env_id)
    try:
        targets = []
        for i in range(n):
            _, info = env.reset(seed=int(seed) + i)
            if "target" not in info:
                raise ValueError(f"{env_id} does not report info['target'] on reset")
            targets.append(np.asarray(info["target"], dtype=float).copy())
    finally:
        if created:
            env.close()
    return targets


def evaluate_policy_costs(
    policy: Any,
    env: gym.Env | str,
    targets: Sequence[np.ndarray] | None = None,
    seed: int = 0,
    *,
    n_episodes: int | None = None,
    max_steps: int | None = None,
    stop_above: float | None = None,
) -> np.ndarray:
    """Per-episode costs ``-sum(rewards)`` of ``policy``.

    :param policy: an object with SB3's ``predict`` or a callable ``obs -> action``.
    :param env: an env or an env id.
    :param targets: one target per episode (``None``: no targets; then give ``n_episodes``).
    :param seed: episode ``i`` resets with ``seed + i``.
    :param max_steps: cap on the steps per episode (default: the env's own limit).
    :param stop_above: stop early once the summed cost exceeds this (an exact early exit of a
        "mean <= threshold" test for costs >= 0).
    :return: ``[n]`` costs (fewer with ``stop_above``).
    """
    check_int("seed", seed, 0)
    if targets is None:
        if n_episodes is None or n_episodes < 1:
            raise ValueError("give targets or n_episodes >= 1")
        options: list[dict | None] = [None] * int(n_episodes)
    else:
        if len(targets) < 1:
            raise ValueError("targets must hold at least one target")
        options = [{"target": np.asarray(t, dtype=float)} for t in targets]
    if hasattr(policy, "predict") or not callable(policy):
        act = as_policy(policy)
    else:
        act = lambda obs, t: np.asarray(policy(obs), dtype=float).reshape(-1)  # noqa: E731
    env, created = make_env(env)
    try:
        costs: list[float] = []
        for i, o in enumerate(options):
            costs.append(run_episode(env, act, seed=int(seed) + i, options=o,
                                     max_steps=max_steps).cost)
            if stop_above is not None and sum(costs) > stop_above:
                break
    finally:
        if created:
            env.close()
    return np.asarray(costs)


def evaluate_policy_cost(policy: Any, env: gym.Env | str, *args: Any, **kwargs: Any) -> float:
    """Mean of :func:`evaluate_policy_costs` (the same arguments)."""
    return float(np.mean(evaluate_policy_costs(policy, env, *args, **kwargs)))


def _is_mujoco_env(env: gym.Env) -> bool:
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

    return isinstance(env.unwrapped, MujocoEnv)


def has_true_model(env: gym.Env) -> bool:
    """Whether :func:`oracle_policy` can build ``env``'s true model (arm or MuJoCo)."""
    return hasattr(env.unwrapped, "dynamics_model") or _is_mujoco_env(env)


def oracle_policy(
    env: gym.Env,
    planner: PlannerConfig | None = None,
    *,
    seed: int = 0,
    model: str = "dynamics_model",
    cost_fn: Callable | None = None,
    state_map: Any = None,
    terminal_cost_fn: Callable | None = None,
    termination_fn: Callable | None = None,
    state_fn: Callable | None = None,
    obs_fn: Callable | None = None,
) -> ReplanEvery:
    """The agent's controller (:func:`agents.planning.make_policy`) on the TRUE model of ``env``:
    ``env.unwrapped.<model>()``, else a Gymnasium ``MujocoEnv``'s own physics from its true state
    (docs/agent.md, the ``oracle_policy`` row and "The oracle of any MuJoCo env").

    :param planner: the planner settings (``None``: ``PlannerConfig()``).
    :param seed: seeds CEM's samples (the agent passes its ``config.seed``).
    :param cost_fn: / ``state_map`` (or ``state_fn``/``obs_fn``), ``terminal_cost_fn``,
        ``termination_fn``: the task's (default: the env's own quadratic cost).
    :raises ValueError: an env with no true model, or no cost given and no ``cost_Q``/``cost_R``.
    """
    planner = PlannerConfig() if planner is None else planner
    if not isinstance(planner, PlannerConfig):
        raise TypeError(f"planner must be an agents.config.PlannerConfig, got "
                        f"{type(planner).__name__}")
    if model not in ("dynamics_model", "analytic_model"):
        raise ValueError(f"model must be 'dynamics_model' or 'analytic_model', got {model!r}")
    factory = getattr(env.unwrapped, model, None)
    if factory is None and not _is_mujoco_env(env):
        raise ValueError(
            f"{env.unwrapped!r} has no {model}() and is not a Gymnasium MujocoEnv: there is no "
            "true model to build the oracle from"
        )
    spec = env_spec(env)
    if state_fn is not None or obs_fn is not None:
        if state_map is not None:
            raise ValueError("give state_map or state_fn/obs_fn, not both")
        state_map = StateMap(state_fn, obs_fn)  # refuses one without the other
    if cost_fn is None:
        default = default_task_for_env(env)
        if default is None:
            raise ValueError("the env has no cost_Q/cost_R; give cost_fn and state_map")
        cost_fn, default_map = default
        state_map = state_map or default_map
    true_state_env = None
    if factory is None:  # any Gymnasium MuJoCo env: plan on [qpos, qvel, observation]
        from envs.mujoco_model import MujocoDynamics, ObservedDynamics

        true_model = ObservedDynamics(MujocoDynamics(env), env)
        if true_model.obs_dim != spec.obs_dim:
            raise ValueError(
                f"the env's _get_obs returns {true_model.obs_dim} values, its observation_space "
                f"has {spec.obs_dim}"
            )
        n = true_model.n
        state_map = StateMap(state_fn=_oracle_state_fn, obs_fn=lambda s, ref: s[n:])
        true_state_env = env
    else:
        true_model = factory()
        state_map = StateMap() if state_map is None else state_map
    task_cost = ObservationCost(cost_fn, state_map, spec, true_model.state_dim,
                                terminal_cost_fn=terminal_cost_fn)
    return make_policy(planner, true_model, task_cost, seed=seed, termination_fn=termination_fn,
                       particles=1 if planner.cem.particles > 1 else None,
                       true_state_env=true_state_env)

def _oracle_state_fn(obs: np.ndarray) -> np.ndarray:
    raise ValueError("the MuJoCo oracle reads its state from the env (TrueStatePolicy), not "
                     "from an observation")


def cached_costs(
    cache_dir: str | os.PathLike | None, key: dict[str, Any], compute: Callable[[], np.ndarray]
) -> np.ndarray:
    """``compute()`` memoised in ``<cache_dir>/oracle_<sha256(key)[:16]>.json`` (atomic write;
    ``key``: a JSON-serialisable dict of what the costs depend on; ``cache_dir=None``: off)."""
    if cache_dir is None:
        return np.asarray(compute(), dtype=float)
    text = json.dumps(key, sort_keys=True, default=json_default)
    path = Path(cache_dir) / f"oracle_{hashlib.sha256(text.encode()).hexdigest()[:16]}.json"
    if path.is_file():
        stored = json.loads(path.read_text())
        if stored.get("key") == json.loads(text):
            return np.asarray(stored["costs"], dtype=float)
    costs = np.asarray(compute(), dtype=float)
    atomic_write_text(path, json.dumps({"key": json.loads(text), "costs": costs.tolist()}))
    return costs


def physics_fingerprint(env: gym.Env) -> str:
    """sha256 (16 hex digits) of the physics the env simulates: its compiled ``MjModel`` saved
    as MJB bytes (every parameter, not the source code)."""
    import mujoco

    model = getattr(env.unwrapped, "model", None)
    if not isinstance(model, mujoco.MjModel):
        raise ValueError(f"{env.unwrapped!r} has no compiled MuJoCo model (env.unwrapped.model)")
    buf = np.empty(mujoco.mj_sizeModel(model), np.uint8)
    mujoco.mj_saveModel(model, None, buf)
    return hashlib.sha256(buf.tobytes()).hexdigest()[:16]


def oracle_cache_key(
    env: gym.Env,
    task: dict[str, Any],
    targets: Sequence[np.ndarray] | None,
    seed: int,
    *,
    n_episodes: int,
    episode_steps: int,
    planner: dict[str, Any],
    optimizer_options: ILQROptions | None = None,
) -> dict[str, Any]:
    """What the oracle's costs depend on (the key of :func:`cached_costs`): the env's physics
    and fingerprint, the task (``task``: the cost's and state map's ``to_dict()``), targets,
    seed, episode count and length, ``planner`` settings, iLQR's ``optimizer_options`` (default
    ``ILQROptions()``) and ``mbtsr.__version__`` (a release invalidates every entry)."""
    options = ILQROptions() if optimizer_options is None else optimizer_options
    return {
        "mbtsr": mbtsr.__version__,
        "physics": physics_fingerprint(env),
        "env": env_fingerprint(env),
        "task": task,
        "targets": None if targets is None else [np.asarray(t, float).tolist() for t in targets],
        "eval_seed": int(seed),
        "eval_episodes": int(n_episodes),
        "episode_steps": int(episode_steps),
        "planner": dict(planner),
        "optimizer_options": dataclasses.asdict(options),
    }


def solved_threshold(oracle: float, ratio: float = 1.2) -> float:
    """The "solved" cost threshold ``ratio * oracle`` (costs are >= 0)."""
    if not np.isfinite(oracle) or oracle < 0:
        raise ValueError(f"oracle must be a finite cost >= 0, got {oracle!r}")
    if not np.isfinite(ratio) or ratio < 1:
        raise ValueError(f"ratio must be a finite number >= 1, got {ratio!r}")
    return float(ratio * oracle)


class Evaluator:
    """The agent's evaluation: its policy on fixed episodes in a copy of the training env, scored
    against the oracle (:func:`oracle_policy`), whose costs are computed once and kept.

    :param env: the training env (the evaluation env is ``gym.make(env.spec)``).
    :param config: the agent's config.
    :param episode_steps: the episode length.
    :param task: the oracle's ``cost_fn``, ``state_map``, ``terminal_cost_fn``, ``termination_fn``.
    """

    def __init__(self, env: gym.Env | None, config: AgentConfig, episode_steps: int,
                 **task: Any) -> None:
        self.env, self.config, self.episode_steps, self.task = env, config, episode_steps, task
        self.eval_targets: list[np.ndarray] | None = None
        self.oracle_costs: np.ndarray | None = None
        self.oracle_seconds = 0.0  # computing the oracle, booked apart from the evaluation
        self._env: gym.Env | None = None

    def due(self, episode: int, env_steps: int, *, steps: int = 0, last: bool = False) -> bool:
        """Whether to evaluate after ``episode`` (its ``steps`` steps ended at ``env_steps``;
        ``last``: the final score of a ``learn`` call); docs/agent.md, "Evaluation"."""
        ev, first = self.config.evaluation, self.config.collection.n_excitation_episodes - 1
        if (ev.every == 0 and ev.every_steps == 0) or episode < first:
            return False
        k = ev.every_steps
        return (last or (ev.every > 0 and (episode - first) % ev.every == 0)
                or (k > 0 and env_steps // k > (env_steps - steps) // k))

    def eval_env(self) -> gym.Env:
        """The evaluation env, ``gym.make(env.spec)`` (made once)."""
        if self._env is None:
            spec = getattr(self.env, "spec", None)
            if spec is None:
                raise ValueError("evaluation needs an env made by gym.make (env.spec is None)")
            self._env = gym.make(spec)
        return self._env

    def targets(self) -> list[np.ndarray] | None:
        """The evaluation targets (drawn once; ``None`` for an env without targets)."""
        if self.eval_targets is None:
            env, ev = self.eval_env(), self.config.evaluation
            _, info = env.reset(seed=ev.seed)
            if "target" in info:
                self.eval_targets = evaluation_targets(ev.episodes, ev.seed, env)
        return self.eval_targets

    def problem(self, i: int) -> tuple[np.ndarray | None, int]:
        """``(target or None, reset seed)`` of evaluation episode ``i``."""
        targets = self.targets()
        return None if targets is None else targets[i], self.config.evaluation.seed + i

    def setup(self) -> tuple[gym.Env, dict[str, Any]]:
        """``(env, keyword arguments)`` that :func:`evaluate_policy_costs` scores a policy with
        on these episodes (with ``self.eval_targets`` and ``evaluation.seed``)."""
        kwargs: dict[str, Any] = {"max_steps": self.episode_steps}
        if self.targets() is None:
            kwargs["n_episodes"] = self.config.evaluation.episodes
        return self.eval_env(), kwargs

    def evaluate(self, policy: Any, *, complete: bool = False) -> dict[str, Any]:
        """Score ``policy`` (SB3-style ``predict``) on the evaluation episodes.

        :param complete: run every episode (no early exit), as the final score of ``learn``.

        :return: the log fields ``eval_cost`` (mean cost, ``None`` if stopped early),
            ``eval_return`` (mean return) and ``eval_returns`` (per episode), ``oracle_cost``,
            ``cost_ratio`` (``sum(agent) / sum(oracle)`` over the oracle's episodes, a lower
            bound when the evaluation stopped early), ``eval_episodes_run`` and ``solved``.
        """
        ev = self.config.evaluation
        env, kwargs = self.setup()
        oracle = None if ev.solved_return is not None else self.oracle()
        stop_above = None
        if oracle is not None and ev.early_exit and not complete and np.all(oracle >= 0):
            stop_above = ev.solved_ratio * float(np.sum(oracle))
        costs = evaluate_policy_costs(policy, env, self.eval_targets, ev.seed,
                                      stop_above=stop_above, **kwargs)
        complete = len(costs) == ev.episodes
        returns = [float(-c) for c in costs]
        out = {**NOT_EVALUATED, "eval_returns": returns, "eval_episodes_run": len(costs)}
        if complete:
            out.update(eval_cost=float(np.mean(costs)), eval_return=float(np.mean(returns)))
        if ev.solved_return is not None:
            out["solved"] = bool(complete and out["eval_return"] >= ev.solved_return)
            return out
        if oracle is None:
            return out
        total = float(np.sum(oracle))
        ratio = float(np.sum(costs)) / total if total > 0 else math.inf
        out.update(oracle_cost=float(np.mean(oracle)), cost_ratio=ratio,
                   solved=bool(complete and ratio <= ev.solved_ratio))
        return out

    def oracle_policy(self, env: gym.Env) -> ReplanEvery:
        """The oracle's controller on ``env`` (:func:`oracle_policy` with the agent's planner,
        seed and task functions)."""
        return oracle_policy(env, self.config.planner, seed=self.config.seed, **self.task)

    def oracle(self) -> np.ndarray | None:
        """Per-episode costs of the oracle (computed once, then kept; ``None``: the env has
        no true model, or the task no written cost: a learned reward has no oracle). The
        seconds spent computing it add to ``oracle_seconds``."""
        if (self.oracle_costs is not None or not has_true_model(self.eval_env())
                or self.task["cost_fn"] is None):  # a learned reward: no written cost to plan on
            return self.oracle_costs
        cfg, task = self.config, self.task
        env, kwargs = self.setup()

        def compute() -> np.ndarray:
            tic = time.perf_counter()
            try:
                return evaluate_policy_costs(self.oracle_policy(env), env, self.eval_targets,
                                             cfg.evaluation.seed, **kwargs)
            finally:
                self.oracle_seconds += time.perf_counter() - tic

        key: dict[str, Any] = {}
        cache_dir = cfg.evaluation.oracle_cache_dir
        cost_fn, state_map = task["cost_fn"], task["state_map"]
        if not (isinstance(cost_fn, QuadraticTargetCost) and state_map.serializable
                and task["terminal_cost_fn"] is None and task["termination_fn"] is None
                and _is_mujoco_env(env)):
            cache_dir = None  # user functions (or non-MuJoCo physics) cannot be part of a key
        if cache_dir is not None:
            key = oracle_cache_key(
                env, {"cost": cost_fn.to_dict(), "state_map": state_map.to_dict()},
                self.eval_targets, cfg.evaluation.seed, n_episodes=cfg.evaluation.episodes,
                episode_steps=self.episode_steps,
                planner={**dataclasses.asdict(cfg.planner), "seed": cfg.seed},
            )
        self.oracle_costs = cached_costs(cache_dir, key, compute)
        return self.oracle_costs

    def take_oracle_seconds(self) -> float:
        """The oracle seconds not yet booked to an episode (and reset them to 0)."""
        seconds, self.oracle_seconds = self.oracle_seconds, 0.0
        return seconds

    def compute_oracle(self) -> float | None:
        """Compute (or fetch from the cache) the oracle's costs now, outside ``learn`` (the
        seconds are booked to no episode); return their mean (``None``: no true model)."""
        pending = self.oracle_seconds
        costs = self.oracle()
        self.oracle_seconds = pending
        return None if costs is None else float(np.mean(costs))

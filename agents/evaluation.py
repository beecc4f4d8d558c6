"""Evaluation protocol for reach tasks: fixed random targets, episode cost, and the oracle.

"Solved" (issue 6): the mean episode cost of a policy over ``n`` evaluation episodes with
random targets is within ``ratio`` (1.2) times the mean cost of MPC with the TRUE model (the
oracle, :func:`oracle_cost`) on the same targets and the same initial states. The episode cost
is ``-sum(rewards)``, the env's own measure, so any policy (the JacProp agent, an SB3 baseline,
a hand-written controller) is scored the same way::

    targets = evaluation_targets(10, seed=1000)
    oracle = oracle_cost("mbtsr/TwoLinkArm-v0", targets, horizon=30, seed=1000)
    mine = evaluate_policy_cost(sb3_model, "mbtsr/TwoLinkArm-v0", targets, seed=1000)
    solved = mine <= solved_threshold(oracle)

Episode ``i`` is reset with ``seed + i`` and ``options={"target": targets[i]}``.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

__all__ = [
    "ARM_ID",
    "EpisodeRecord",
    "make_env",
    "run_episode",
    "evaluation_targets",
    "evaluate_policy_costs",
    "evaluate_policy_cost",
    "oracle_policy",
    "oracle_cost",
    "cached_costs",
    "code_fingerprint",
    "solved_threshold",
]

ARM_ID = "mbtsr/TwoLinkArm-v0"


def make_env(env: gym.Env | str, **kwargs: Any) -> tuple[gym.Env, bool]:
    """``(env, created)``: ``env`` itself, or ``gym.make(env, **kwargs)`` for an id (the
    project's ``mbtsr/`` envs are registered by importing :mod:`envs`)."""
    if isinstance(env, gym.Env):
        return env, False
    if not isinstance(env, str):
        raise TypeError(f"env must be a gymnasium.Env or an env id string, got {env!r}")
    if env.startswith("mbtsr/"):
        import envs  # noqa: F401  (registers the mbtsr/ ids)
    return gym.make(env, **kwargs), True


@dataclass
class EpisodeRecord:
    """One episode in a real env.

    ``obs: [T+1, obs_dim]``, ``actions: [T, m]``, ``rewards: [T]``; ``states: [T+1, k]`` the
    env's ``info["state"]`` when it reports one; ``frames`` rendered images (``render=True``);
    wall times of the policy and of the env steps.
    """

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    states: np.ndarray | None
    terminated: bool
    info0: dict = field(default_factory=dict)
    frames: list = field(default_factory=list)
    time_policy: float = 0.0
    time_env: float = 0.0

    @property
    def cost(self) -> float:
        """Episode cost ``-sum(rewards)``."""
        return float(-np.sum(self.rewards))

    @property
    def T(self) -> int:  # noqa: N802
        return self.actions.shape[0]


def run_episode(
    env: gym.Env,
    act: Callable[[np.ndarray, int], np.ndarray],
    *,
    seed: int | None,
    options: dict | None = None,
    max_steps: int | None = None,
    render: bool = False,
) -> EpisodeRecord:
    """Roll out ``act(obs, t) -> action`` in ``env`` until termination, truncation or
    ``max_steps``. Actions are clipped to the action space."""
    low, high = env.action_space.low, env.action_space.high
    obs, info = env.reset(seed=seed, options=options)
    obs_list, act_list, rew_list = [np.asarray(obs, dtype=float)], [], []
    states = [info["state"]] if "state" in info else None
    frames = [env.render()] if render else []
    t_policy = t_env = 0.0
    terminated = False
    t = 0
    while max_steps is None or t < max_steps:
        tic = time.perf_counter()
        a = np.clip(np.asarray(act(obs_list[-1], t), dtype=float), low, high)
        # record exactly what the env receives (the action space's dtype, e.g. float32)
        a_env = a.astype(env.action_space.dtype)
        a = a_env.astype(float)
        tac = time.perf_counter()
        obs, reward, terminated, truncated, info = env.step(a_env)
        t_env += time.perf_counter() - tac
        t_policy += tac - tic
        obs_list.append(np.asarray(obs, dtype=float))
        act_list.append(a)
        rew_list.append(float(reward))
        if states is not None:
            states.append(info["state"])
        if render:
            frames.append(env.render())
        t += 1
        if terminated or truncated:
            break
    m = env.action_space.shape[0]
    return EpisodeRecord(
        obs=np.asarray(obs_list),
        actions=np.asarray(act_list, dtype=float).reshape(-1, m),
        rewards=np.asarray(rew_list),
        states=None if states is None else np.asarray(states, dtype=float),
        terminated=bool(terminated),
        frames=frames,
        time_policy=t_policy,
        time_env=t_env,
    )


def evaluation_targets(
    n: int = 10, seed: int = 0, env_id: str | gym.Env = ARM_ID
) -> list[np.ndarray]:
    """``n`` targets drawn by the env's own target distribution: ``info["target"]`` after
    ``reset(seed=seed + i)``.

    :param n: number of targets (>= 1).
    :param seed: base seed (>= 0).
    :param env_id: a registered id (or an instance) of an env that reports ``info["target"]``.
    """
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise ValueError(f"n must be an integer >= 1, got {n!r}")
    _check_seed(seed)
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


def _policy_step_fn(policy: Any) -> Callable[[np.ndarray, int], np.ndarray]:
    """Wrap an SB3-style ``predict`` (threading its recurrent state) or a callable."""
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
        return lambda obs, t: np.asarray(policy(obs), dtype=float).reshape(-1)
    raise TypeError(
        f"policy must have a predict(obs, state, episode_start, deterministic) method or be a "
        f"callable obs -> action, got {type(policy).__name__}"
    )


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

    :param policy: an object with SB3's ``predict(obs, state, episode_start, deterministic)``
        (our agent, an SB3 model, :class:`agents.planner.MPCPolicy`) or a callable
        ``obs -> action``.
    :param env: an env or an env id.
    :param targets: one target per episode, passed as ``options={"target": ...}``; ``None``
        for envs without targets (then give ``n_episodes``).
    :param seed: episode ``i`` resets with ``seed + i``.
    :param max_steps: cap on the steps per episode (default: the env's own limit).
    :param stop_above: stop early once the summed cost exceeds this (costs are >= 0, so the
        full sum would too): an exact early exit of a "mean <= threshold" test. The result then
        holds fewer than ``n`` costs.
    :return: ``[n]`` costs (fewer with ``stop_above``).
    """
    _check_seed(seed)
    if targets is None:
        if n_episodes is None or n_episodes < 1:
            raise ValueError("give targets or n_episodes >= 1")
        options: list[dict | None] = [None] * int(n_episodes)
    else:
        if len(targets) < 1:
            raise ValueError("targets must hold at least one target")
        options = [{"target": np.asarray(t, dtype=float)} for t in targets]
    act = _policy_step_fn(policy)
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


def evaluate_policy_cost(
    policy: Any,
    env: gym.Env | str,
    targets: Sequence[np.ndarray] | None = None,
    seed: int = 0,
    *,
    n_episodes: int | None = None,
    max_steps: int | None = None,
) -> float:
    """Mean of :func:`evaluate_policy_costs`."""
    return float(
        np.mean(
            evaluate_policy_costs(
                policy, env, targets, seed, n_episodes=n_episodes, max_steps=max_steps
            )
        )
    )


def oracle_policy(
    env: gym.Env,
    horizon: int,
    *,
    iterations: int = 2,
    first_plan_iterations: int = 20,
    terminal_weight: float = 1.0,
    model: str = "dynamics_model",
    cost_fn: Callable | None = None,
    state_map: Any = None,
):
    """MPC on the TRUE model of ``env`` (``env.unwrapped.dynamics_model()`` -- MuJoCo -- or
    ``analytic_model()``), with the env's own quadratic cost unless ``cost_fn``/``state_map``
    are given. Same controller as the agent, only the model differs.

    The true model's state must be the agent's model state (the arm: ``obs[:4]``)."""
    from agents.planner import MPCPolicy, PlannerCosts
    from agents.task import ObservationCost, default_task_for_env, env_spec

    if model not in ("dynamics_model", "analytic_model"):
        raise ValueError(f"model must be 'dynamics_model' or 'analytic_model', got {model!r}")
    factory = getattr(env.unwrapped, model, None)
    if factory is None:
        raise ValueError(f"{env.unwrapped!r} has no {model}() to build the oracle from")
    true_model = factory()
    spec = env_spec(env)
    if cost_fn is None:
        default = default_task_for_env(env)
        if default is None:
            raise ValueError("the env has no cost_Q/cost_R; give cost_fn and state_map")
        cost_fn, default_map = default
        state_map = state_map or default_map
    if state_map is None:
        from agents.task import StateMap

        state_map = StateMap()
    task_cost = ObservationCost(cost_fn, state_map, spec, true_model.state_dim)
    return MPCPolicy(
        true_model,
        PlannerCosts(task_cost, terminal_weight),
        spec,
        horizon=horizon,
        iterations=iterations,
        first_plan_iterations=first_plan_iterations,
    )


def oracle_cost(
    env: gym.Env | str,
    targets: Sequence[np.ndarray],
    horizon: int,
    *,
    seed: int = 0,
    iterations: int = 2,
    first_plan_iterations: int = 20,
    terminal_weight: float = 1.0,
    model: str = "dynamics_model",
    return_costs: bool = False,
) -> float | np.ndarray:
    """Mean episode cost of MPC with the TRUE model on ``targets`` (see :func:`oracle_policy`
    and :func:`evaluate_policy_costs`; the same ``seed`` gives the same initial states).

    :param return_costs: return the per-episode costs ``[n]`` instead of the mean.
    """
    env, created = make_env(env)
    try:
        policy = oracle_policy(
            env,
            horizon,
            iterations=iterations,
            first_plan_iterations=first_plan_iterations,
            terminal_weight=terminal_weight,
            model=model,
        )
        costs = evaluate_policy_costs(policy, env, targets, seed)
    finally:
        if created:
            env.close()
    return costs if return_costs else float(np.mean(costs))


def cached_costs(
    cache_dir: str | os.PathLike | None, key: dict[str, Any], compute: Callable[[], np.ndarray]
) -> np.ndarray:
    """``compute()`` memoised in ``<cache_dir>/oracle_<sha256(key)[:16]>.json`` (atomic write).

    The oracle is deterministic, so runs that share env, targets, seeds and MPC settings (all in
    ``key``, a JSON-serialisable dict) can share its costs. ``cache_dir=None`` disables it.
    """
    if cache_dir is None:
        return np.asarray(compute(), dtype=float)
    from agents.checkpoint import atomic_write_text

    text = json.dumps(key, sort_keys=True, default=_json_default)
    path = Path(cache_dir) / f"oracle_{hashlib.sha256(text.encode()).hexdigest()[:16]}.json"
    if path.is_file():
        stored = json.loads(path.read_text())
        if stored.get("key") == json.loads(text):
            return np.asarray(stored["costs"], dtype=float)
    costs = np.asarray(compute(), dtype=float)
    atomic_write_text(path, json.dumps({"key": json.loads(text), "costs": costs.tolist()}))
    return costs


def code_fingerprint(*objects: Any, packages: Sequence[Any] = ()) -> str:
    """sha256 over the source files defining ``objects`` (modules, classes, functions) and over
    every ``.py``/``.xml`` file in the folders of ``packages`` (an env's package with its
    assets): part of a cache key, so that cached oracle costs are recomputed when the env or
    solver code changes."""
    import inspect

    files = {inspect.getsourcefile(o) or "" for o in objects}
    for pkg in packages:
        folder = Path(inspect.getsourcefile(pkg) or "").parent
        files |= {str(f) for f in folder.rglob("*") if f.suffix in (".py", ".xml")}
    h = hashlib.sha256()
    for path in sorted(f for f in files if f and Path(f).is_file()):
        h.update(Path(path).read_bytes())
    return h.hexdigest()[:16]


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


def solved_threshold(oracle: float, ratio: float = 1.2) -> float:
    """The "solved" cost threshold ``ratio * oracle`` (costs are >= 0)."""
    if not np.isfinite(oracle) or oracle < 0:
        raise ValueError(f"oracle must be a finite cost >= 0, got {oracle!r}")
    if not np.isfinite(ratio) or ratio < 1:
        raise ValueError(f"ratio must be a finite number >= 1, got {ratio!r}")
    return float(ratio * oracle)


def _check_seed(seed: Any) -> None:
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")

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

import abc
import hashlib
import json
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import casadi as ca
import gymnasium as gym
import numpy as np

from agents.tasks import ObservationCost
from mbtsr.costs import CasadiCost
from mbtsr.episode import EpisodeRecord, as_policy, run_episode
from mbtsr.ilqr import ILQROptions, ilqr
from mbtsr.mpc import MPC, MPCOptions
from mbtsr.validation import as_array, check_callable, check_int

__all__ = [
    "EpisodeRecord",
    "MPCPolicy",
    "SB3Predictor",
    "make_env",
    "mpc_policy",
    "planner_cost",
    "run_episode",
    "evaluation_targets",
    "evaluate_policy_costs",
    "evaluate_policy_cost",
    "oracle_policy",
    "oracle_cost",
    "has_true_model",
    "TrueStatePolicy",
    "cached_costs",
    "oracle_cache_key",
    "physics_fingerprint",
    "solved_threshold",
]


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


def planner_cost(task_cost: ObservationCost, terminal_weight: float = 1.0) -> CasadiCost:
    """The planner's :class:`mbtsr.costs.CasadiCost` of a task, compiled once: stage
    ``cost_fn(obs_fn(s, p), a)`` and terminal ``terminal_weight * cost_fn(obs_fn(s, p), 0)`` on
    the model state ``s``, with the reference observation ``p = obs [obs_dim]`` as the cost
    parameter (for the arm only its target entries matter). A new target is a new ``params``,
    not a new function."""
    n, m, d = task_cost.state_dim, task_cost.spec.act_dim, task_cost.spec.obs_dim
    s, a, p, t = ca.SX.sym("s", n), ca.SX.sym("a", m), ca.SX.sym("p", d), ca.SX.sym("t")
    stage = ca.Function("stage", [s, a, t, p], [task_cost.stage(s, a, p)])
    terminal = ca.Function(
        "terminal", [s, p], [float(terminal_weight) * task_cost.terminal(s, p)]
    )
    return CasadiCost(stage, terminal, n, m)


class SB3Predictor(abc.ABC):
    """Stable-Baselines3's ``predict`` over ``_act(observation, state)``: the MPC policies and
    the agent. ``episode_start`` forces a cold start (``state=None``); ``deterministic`` is
    unused (MPC is deterministic), kept for SB3 compatibility."""

    @abc.abstractmethod
    def _act(self, observation: Any, state: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """One step from ``observation`` with the recurrent ``state`` (``None``: cold start)."""

    def predict(
        self,
        observation: np.ndarray,
        state: np.ndarray | None = None,
        episode_start: np.ndarray | bool | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One step (Stable-Baselines3 signature).

        :param observation: ``[obs_dim]`` current observation.
        :param state: the recurrent state returned by the previous call (the remaining plan),
            or ``None`` (cold start, also forced by ``episode_start``).
        :param episode_start: ``True`` at the first step of an episode.
        :param deterministic: unused (MPC is deterministic); kept for SB3 compatibility.
        :return: ``(action [m], next_state)``.
        """
        if episode_start is not None and bool(np.any(episode_start)):
            state = None
        return self._act(observation, state)


class MPCPolicy(SB3Predictor):
    """Stable-Baselines3's ``predict`` on observations for an :class:`mbtsr.mpc.MPC`.

    Maps the observation to the model state (``task_cost.state_map``) and to the cost
    parameters (the observation itself: see :func:`planner_cost`), solves from there, and
    returns the first action with the rest of the plan, shifted by one step, as the recurrent
    ``state`` (the warm start of the next call), so ``predict`` is a pure function of its
    arguments. The same adapter serves the agent (frozen learned model) and the oracle (true
    model).

    :param mpc: the controller (its cost from :func:`planner_cost`).
    :param task_cost: the task (observation/state maps, env spec).
    :param termination_fn: ``obs [..., obs_dim] -> bool [...]``, where the env would end the
        episode, or ``None``. The optimizer (iLQR or CEM) then scores plans on the episode's
        own cost: stage costs after a predicted termination are dropped
        (:func:`mbtsr.costs.truncated_total`).
    """

    def __init__(self, mpc: MPC, task_cost: ObservationCost,
                 termination_fn: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        if not isinstance(mpc, MPC):
            raise TypeError(f"mpc must be a mbtsr.mpc.MPC, got {type(mpc).__name__}")
        if termination_fn is not None:
            check_callable("termination_fn", termination_fn, "obs -> bool")
        self.mpc = mpc
        self.task_cost = task_cost
        self.spec = task_cost.spec
        self.state_map = task_cost.state_map
        self.termination_fn = termination_fn
        self.last_result = None
        self._obs_maps: dict[int, ca.Function] = {}  # obs_of_state mapped over N states
        if termination_fn is not None:
            s, p = ca.SX.sym("s", task_cost.state_dim), ca.SX.sym("p", self.spec.obs_dim)
            self._obs_of_state = ca.Function("obs_of_state", [s, p], [
                ca.SX(self.state_map.observation(s, p))])

    @property
    def model(self) -> Any:
        """The planning model."""
        return self.mpc.model

    def _act(self, observation: Any, state: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """One MPC step: ``state`` is the ``[H, m]`` plan returned by the previous call (the
        warm start) or ``None`` (a cold start); returns ``(action [m], next_state [H, m])``."""
        obs = as_array("observation", observation, (self.spec.obs_dim,))
        if state is not None:
            state = np.asarray(state, dtype=float)
            if state.shape != (self.mpc.horizon, self.spec.act_dim):
                raise ValueError(
                    f"state must be the [H={self.mpc.horizon}, m={self.spec.act_dim}] plan "
                    f"returned by predict, got {list(state.shape)}"
                )
        res = self.mpc.solve(self.model_state(obs), 0, params=obs, warm_start=state,
                             **self._solve_kwargs(obs))
        self.last_result = res
        U = np.asarray(res.U, dtype=float)
        action = np.clip(U[0], self.spec.u_min, self.spec.u_max)
        return action, np.concatenate([U[1:], U[-1:]], axis=0)

    def model_state(self, obs: np.ndarray) -> np.ndarray:
        """The planner's start state for this observation (the task's state map)."""
        return self.state_map.state(obs)

    def _solve_kwargs(self, obs: np.ndarray) -> dict[str, Any]:
        """Extra keyword arguments of the optimizer for this observation: the predicted
        termination ``terminated(X [..., n]) -> bool [...]`` on model states, through the
        observation map (the current observation fills what the state leaves out)."""
        if self.termination_fn is None:
            return {}
        fn, obs_ref = self.termination_fn, np.asarray(obs, dtype=float)

        def terminated(X: np.ndarray) -> np.ndarray:
            flat = X.reshape(-1, X.shape[-1])
            N = flat.shape[0]
            if N not in self._obs_maps:  # the line search calls with a few fixed batch sizes
                self._obs_maps[N] = self._obs_of_state.map(N)
            obs = np.asarray(self._obs_maps[N](flat.T, np.repeat(obs_ref[:, None], N, axis=1))).T
            return np.asarray(fn(obs), dtype=bool).reshape(X.shape[:-1])

        return {"terminated": terminated}


def mpc_policy(
    model: Any,
    task_cost: ObservationCost,
    *,
    horizon: int,
    iterations: int,
    first_plan_iterations: int,
    terminal_weight: float = 1.0,
    cost: CasadiCost | None = None,
    optimizer: Callable[..., Any] = ilqr,
    optimizer_options: Any = None,
    termination_fn: Callable[[np.ndarray], np.ndarray] | None = None,
) -> MPCPolicy:
    """The agent's and the oracle's controller: :class:`MPCPolicy` around
    ``MPC(optimizer, planner_cost(task_cost), model, horizon)`` with the env's action box.

    :param model: a planning model (a frozen ensemble, the true model).
    :param cost: the compiled :func:`planner_cost` to reuse (built when ``None``).
    :param optimizer_options: ``None``: iLQR's own defaults (``ILQROptions()``).
    :param termination_fn: see :class:`MPCPolicy`.
    """
    spec = task_cost.spec
    cost = planner_cost(task_cost, terminal_weight) if cost is None else cost
    if optimizer_options is None and optimizer is ilqr:
        optimizer_options = ILQROptions()
    mpc = MPC(
        optimizer, cost, model, horizon, u_min=spec.u_min, u_max=spec.u_max,
        options=MPCOptions(
            iterations_per_step=iterations, first_step_iterations=first_plan_iterations,
            optimizer_options=optimizer_options, warm_start_lambda=False,
        ),
    )
    return MPCPolicy(mpc, task_cost, termination_fn)


def evaluation_targets(
    n: int = 10, seed: int = 0, env_id: str | gym.Env | None = None
) -> list[np.ndarray]:
    """``n`` targets drawn by the env's own target distribution: ``info["target"]`` after
    ``reset(seed=seed + i)``.

    :param n: number of targets (>= 1).
    :param seed: base seed (>= 0).
    :param env_id: a registered id (or an instance) of an env that reports ``info["target"]``
        (``None``: the home arm, ``envs.ARM_ID``).
    """
    if env_id is None:
        from envs import ARM_ID  # here, not at import: importing envs sets MUJOCO_GL

        env_id = ARM_ID
    check_int("n", n, 1)
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
        (our agent, an SB3 model, :class:`MPCPolicy`) or a callable ``obs -> action``.
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


class TrueStatePolicy(MPCPolicy):
    """:class:`MPCPolicy` that plans from the env's TRUE physical state instead of the
    observation: the oracle of a Gymnasium MuJoCo env. Each call reads ``qpos, qvel`` of the live
    ``env`` (after ``reset`` its initial state; mocap poses too, e.g. a target marker) and
    starts the plan at ``model.lift(x) = [x, observation(x)]`` (an
    :class:`envs.mujoco_model.ObservedDynamics`). Only valid inside episodes of that ``env``."""

    def __init__(self, mpc: MPC, task_cost: ObservationCost, env: gym.Env,
                 termination_fn: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        super().__init__(mpc, task_cost, termination_fn)
        self.env = env

    def model_state(self, obs: np.ndarray) -> np.ndarray:
        from envs.mujoco_model import state_of

        dyn, base = self.model.dynamics, self.env.unwrapped
        if dyn.model.nmocap:
            dyn.set_mocap(base.data.mocap_pos, base.data.mocap_quat)
        return self.model.lift(state_of(self.env))


def _is_mujoco_env(env: gym.Env) -> bool:
    from gymnasium.envs.mujoco.mujoco_env import MujocoEnv

    return isinstance(env.unwrapped, MujocoEnv)


def has_true_model(env: gym.Env) -> bool:
    """Whether :func:`oracle_policy` can build the true model of ``env``: it has
    ``dynamics_model()`` (the project's arm) or is a Gymnasium ``MujocoEnv``."""
    return hasattr(env.unwrapped, "dynamics_model") or _is_mujoco_env(env)


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
    terminal_cost_fn: Callable | None = None,
    termination_fn: Callable | None = None,
    optimizer: Callable[..., Any] = ilqr,
    optimizer_options: Any = None,
    state_fn: Callable | None = None,
    obs_fn: Callable | None = None,
) -> MPCPolicy:
    """MPC on the TRUE model of ``env``, with the env's own quadratic cost unless
    ``cost_fn``/``state_map`` are given. Same controller (:func:`mpc_policy`: ``optimizer``
    with ``optimizer_options``, ``iterations`` per step; the agent passes its own planner's) as
    the agent, only the model differs. The true model is

    * ``env.unwrapped.dynamics_model()`` (or ``analytic_model()``) when the env offers one (the
      arm); its state must be the agent's model state (the arm: ``obs[:4]``, via ``state_map``);
    * otherwise, for any Gymnasium ``MujocoEnv`` (Reacher-v5, InvertedPendulum-v5, ...),
      :class:`envs.mujoco_model.MujocoDynamics` lifted to ``z = [qpos, qvel, observation]`` by
      :class:`envs.mujoco_model.ObservedDynamics`: the task's ``cost_fn(obs, a)`` (and
      ``terminal_cost_fn``) is evaluated on the env's own observation of the predicted state,
      and the plan starts from the env's true ``qpos, qvel`` (:class:`TrueStatePolicy`, so the
      returned policy only works on this ``env``). ``state_map`` is ignored there (the true
      state needs no map).

    ``termination_fn`` (the task's, on observations) is respected as by the agent's MPC.
    ``state_fn``/``obs_fn`` (the agent's arguments) build ``state_map`` when it is not given.

    :raises ValueError: an env that has neither (not MuJoCo, no ``dynamics_model()``): it has
        no true model, so no oracle (the agent then reports ``oracle_cost = None``); also when
        no cost is given and the env has no ``cost_Q``/``cost_R``.
    """
    from agents.tasks import StateMap, default_task_for_env, env_spec

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
    kwargs = {"horizon": horizon, "iterations": iterations,
              "first_plan_iterations": first_plan_iterations, "terminal_weight": terminal_weight,
              "termination_fn": termination_fn, "optimizer": optimizer,
              "optimizer_options": optimizer_options}
    if factory is None:  # any Gymnasium MuJoCo env: plan on [qpos, qvel, observation]
        from envs.mujoco_model import MujocoDynamics, ObservedDynamics

        true_model = ObservedDynamics(MujocoDynamics(env), env)
        if true_model.obs_dim != spec.obs_dim:
            raise ValueError(
                f"the env's _get_obs returns {true_model.obs_dim} values, its observation_space "
                f"has {spec.obs_dim}"
            )
        n = true_model.n
        obs_map = StateMap(state_fn=_oracle_state_fn, obs_fn=lambda s, ref: s[n:])
        task_cost = ObservationCost(cost_fn, obs_map, spec, true_model.state_dim,
                                    terminal_cost_fn=terminal_cost_fn)
        policy = mpc_policy(true_model, task_cost, **kwargs)
        return TrueStatePolicy(policy.mpc, task_cost, env, termination_fn)
    true_model = factory()
    if state_map is None:
        state_map = StateMap()
    task_cost = ObservationCost(cost_fn, state_map, spec, true_model.state_dim,
                                terminal_cost_fn=terminal_cost_fn)
    return mpc_policy(true_model, task_cost, **kwargs)


def _oracle_state_fn(obs: np.ndarray) -> np.ndarray:
    raise ValueError("the MuJoCo oracle reads its state from the env (TrueStatePolicy), not "
                     "from an observation")


def oracle_cost(
    env: gym.Env | str,
    targets: Sequence[np.ndarray] | None,
    horizon: int,
    *,
    seed: int = 0,
    return_costs: bool = False,
    n_episodes: int | None = None,
    max_steps: int | None = None,
    **policy_options: Any,
) -> float | np.ndarray:
    """Mean episode cost of MPC with the TRUE model on ``targets``: :func:`oracle_policy`
    (``policy_options``: its keyword arguments, e.g. ``iterations``, ``cost_fn``,
    ``terminal_cost_fn``) scored by :func:`evaluate_policy_costs` (the same ``seed`` gives the
    same initial states).

    :param return_costs: return the per-episode costs ``[n]`` instead of the mean.
    :param targets: ``None`` with ``n_episodes``: envs without targets (Reacher-v5,
        InvertedPendulum-v5).
    :param max_steps: cap on the steps per episode (default: the env's own limit).
    """
    env, created = make_env(env)
    try:
        policy = oracle_policy(env, horizon, **policy_options)
        costs = evaluate_policy_costs(policy, env, targets, seed, n_episodes=n_episodes,
                                      max_steps=max_steps)
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


def physics_fingerprint(env: gym.Env) -> str:
    """sha256 (16 hex digits) of the physics the env simulates: its compiled ``MjModel`` saved
    as MJB bytes (every numeric array, option and size: masses, geometry, actuator gains,
    time step, ...). Changes when a physical parameter does, not when source code is edited."""
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
    """What the oracle's costs depend on, as data (the key of :func:`cached_costs`): the env's
    physics (:func:`physics_fingerprint`) and :func:`agents.checkpoint.env_fingerprint` (id,
    constructor arguments, time step, spaces), the task (``task``: the cost's and the state map's
    ``to_dict()``), the evaluation targets,
    seed, episode count and length, the planner settings (``planner``: horizon, iterations,
    ...; ``optimizer_options``: iLQR's, default ``ILQROptions()`` as :func:`mpc_policy` uses)
    and ``mbtsr.__version__`` (a release invalidates every entry)."""
    import dataclasses

    import mbtsr
    from agents.checkpoint import env_fingerprint

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
    check_int("seed", seed, 0)

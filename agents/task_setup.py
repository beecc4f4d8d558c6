"""The agent's task from its constructor arguments (docs/agent.md, "The cost: a registry task, a
learned reward, or yours"), checked on probe observations at construction, and
:func:`build_agent`, which gives the agent its parts."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from agents.tasks import TASKS, EnvSpec, QuadraticTargetCost, StateMap, Task, default_task_for_env
from mbtsr.reward import FrozenReward, LearnedRewardCost, RewardConfig, RewardFit, RewardModel
from mbtsr.training import holdout_mask
from mbtsr.trajectory import Trajectory
from mbtsr.validation import call_user_fn, check_callable

__all__ = ["LearnedTask", "ResolvedTask", "build_agent", "build_parts", "check_state_map",
           "checked_termination_fn", "probe_observations", "registry_task", "resolve_task"]


@dataclass(frozen=True)
class ResolvedTask:
    """The agent's task after :func:`resolve_task`.

    :param cost_fn: the stage cost on ``(obs, action)`` (CasADi operations), or ``None``: the
        reward is learned from the env's rewards (:class:`LearnedTask`).
    :param state_map: observation <-> model state.
    :param terminal_cost_fn: / ``termination_fn``: the given ones, else the registry task's.
    :param source: where the cost comes from: ``"given"``, ``"saved"``, ``"registry"``, ``"env"``
        (``cost_Q``/``cost_R``) or ``"learned"``.
    :param registry: the name of the registry task (``source="registry"``), else ``None``.
    """

    cost_fn: Callable | None
    state_map: StateMap
    terminal_cost_fn: Callable | None = None
    termination_fn: Callable | None = None
    source: str = "given"
    registry: str | None = None


def registry_task(env_id: str | None) -> Task | None:
    """The task of :data:`agents.tasks.TASKS` whose env id is ``env_id`` (``None``: none)."""
    return next((t for t in (make() for make in TASKS.values()) if t.env_id == env_id), None)


def resolve_task(
    env: gym.Env | None,
    cost_fn: Callable | str | None,
    state_fn: Callable | None,
    obs_fn: Callable | None,
    saved_task: dict | None = None,
    *,
    terminal_cost_fn: Callable | None = None,
    termination_fn: Callable | None = None,
) -> ResolvedTask:
    """The task from the constructor's arguments, first match wins: ``cost_fn="learned"`` (or
    a checkpoint of a learned reward), a given ``cost_fn``, a saved
    :class:`~agents.tasks.QuadraticTargetCost`, the registry's task for the env's id (each
    function only where the caller gave none), the env's own quadratic cost, else a learned
    reward (docs/agent.md, "The cost")."""
    own = {"terminal_cost_fn": terminal_cost_fn, "termination_fn": termination_fn}
    saved_task, env_id = saved_task or {}, getattr(getattr(env, "spec", None), "id", None)
    if isinstance(cost_fn, str) and cost_fn != "learned":
        raise ValueError(f"cost_fn must be a callable, None or 'learned', got {cost_fn!r}")
    if (saved_task.get("learned") and cost_fn not in ("learned", None)) or (
            saved_task and not saved_task.get("learned") and cost_fn == "learned"):
        held = "a learned reward" if saved_task.get("learned") else "a written cost"
        how = "cost_fn='learned' or no cost_fn" if saved_task.get("learned") else "its cost_fn"
        raise ValueError(f"the checkpoint holds {held}: load it with {how}")
    if cost_fn == "learned" or saved_task.get("learned"):
        if terminal_cost_fn is not None:
            raise ValueError("terminal_cost_fn needs a written cost_fn: a learned reward has "
                             "no terminal cost")
        # a known env keeps its task's termination and state maps where none are given
        task = registry_task(env_id)
        if task is not None and state_fn is None:
            state_fn, obs_fn = task.state_fn, task.obs_fn
        if task is not None and termination_fn is None:
            own["termination_fn"] = task.termination_fn
        return ResolvedTask(None, StateMap(state_fn, obs_fn), **own, source="learned")
    if cost_fn is not None:
        return ResolvedTask(cost_fn, StateMap(state_fn, obs_fn), **own)
    if saved_task.get("cost") is not None:
        saved = state_fn is None and saved_task.get("state_map") is not None
        return ResolvedTask(QuadraticTargetCost.from_dict(saved_task["cost"]),
                            StateMap.from_dict(saved_task["state_map"]) if saved
                            else StateMap(state_fn, obs_fn), **own, source="saved")
    task = (TASKS[saved_task["registry"]]() if saved_task.get("registry") in TASKS
            else registry_task(env_id))
    if task is not None and task.cost_fn is not None:
        maps = (state_fn, obs_fn) if state_fn is not None else (task.state_fn, task.obs_fn)
        return ResolvedTask(
            task.cost_fn, StateMap(*maps),
            terminal_cost_fn if terminal_cost_fn is not None else task.terminal_cost_fn,
            termination_fn if termination_fn is not None else task.termination_fn,
            source="registry", registry=task.name)
    default = default_task_for_env(env) if env is not None else None
    if default is not None:
        cost, default_map = default
        return ResolvedTask(cost, default_map if state_fn is None else StateMap(state_fn, obs_fn),
                            **own, source="env")
    return ResolvedTask(None, StateMap(state_fn, obs_fn), **own, source="learned")


class LearnedTask:
    """Stands where :class:`~agents.tasks.ObservationCost` does without a written cost: the
    planner's cost is ``-r_hat(s, a)`` of a :class:`~mbtsr.reward.RewardModel` on the model
    state (0 before its first fit).

    :param state_map: observation <-> model state.
    :param spec: the env's :class:`~agents.tasks.EnvSpec`.
    :param state_dim: the model state's size ``n``.
    :param config: the reward model's settings (seeded by the caller).
    """

    cost_fn = None
    terminal_cost_fn = None

    def __init__(self, state_map: StateMap, spec: EnvSpec, state_dim: int,
                 config: RewardConfig) -> None:
        self.state_map, self.spec, self.state_dim = state_map, spec, int(state_dim)
        self.model = RewardModel(self.state_dim, spec.act_dim, config)

    def frozen(self) -> FrozenReward:
        """The current reward as a :class:`~mbtsr.reward.FrozenReward` (0 before a fit)."""
        if self.model.normalization is None:
            d = self.state_dim + self.spec.act_dim
            return FrozenReward(np.zeros((d, 1)), np.zeros(1), np.zeros(1), 0.0, self.state_dim)
        return self.model.freeze()

    def planner_cost(self, terminal_weight: float) -> LearnedRewardCost:
        """The planner's cost (the observation is its ignored parameter)."""
        return LearnedRewardCost(self.frozen(), terminal_weight=terminal_weight,
                                 param_dim=self.spec.obs_dim)

    def fit(self, trajectories: list[Trajectory]) -> RewardFit | None:
        """Fit (warm start) on every ``(s_t, a_t) -> r_t`` of ``trajectories``; ``None`` while
        they hold too few for the hold-out."""
        S = np.concatenate([t.x[:-1] for t in trajectories])
        A = np.concatenate([t.u for t in trajectories])
        r = np.concatenate([np.asarray(t.meta["rewards"], dtype=float) for t in trajectories])
        held = int(holdout_mask(len(r), self.model.config.holdout).sum())
        if len(r) - held < 1 or (self.model.config.holdout > 0 and held < 1):
            return None
        return self.model.fit(S, A, r)

    def on_observations(self, obs: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """Per-step learned cost ``-r_hat`` of an episode (``obs [T, obs_dim]``, ``actions``)."""
        return -self.frozen().predict(self.state_map.state(obs), np.asarray(actions, float))


def probe_observations(env: gym.Env | None, shape: tuple[int, ...]) -> np.ndarray:
    """Seeded test observations ``shape = [..., obs_dim]`` in ``[-1, 1]``, clipped to the
    env's observation space when there is an env."""
    probe = np.random.default_rng(0).uniform(-1.0, 1.0, shape)
    if env is not None:
        probe = np.clip(probe, env.observation_space.low, env.observation_space.high)
    return probe


def check_state_map(state_map: StateMap, env: gym.Env | None, spec: EnvSpec) -> np.ndarray:
    """Check the state map on one observation and on a batch of three (whole episodes are
    mapped at once): the batch must give the rows of the single calls.

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


def build_agent(agent: Any, env: gym.Env | None, config: Any, spec: EnvSpec,
                fns: dict[str, Any], saved_task: dict | None = None) -> None:
    """Give a :class:`agents.jacprop_agent.JacPropAgent` its task, model, parts and a fresh
    learning state (construction, and :func:`agents.checkpoint.load_agent` before restoring).

    :param agent: the agent whose attributes are set.
    :param env: the env (``None``: an act-only loaded agent).
    :param config: its :class:`agents.config.AgentConfig`.
    :param spec: the env's :class:`agents.tasks.EnvSpec`.
    :param fns: the task functions by name (``None`` where not given).
    :param saved_task: a checkpoint's serialised task, or ``None``.
    """
    agent.env, agent.config, agent.spec = env, config, spec
    agent.env_id = getattr(getattr(env, "spec", None), "id", None)
    # the task: cost on (obs, action) (or a learned reward) and the obs <-> state maps
    agent.task = resolve_task(env, fns["cost_fn"], fns["state_fn"], fns["obs_fn"], saved_task,
                              terminal_cost_fn=fns["terminal_cost_fn"],
                              termination_fn=fns["termination_fn"])
    config = agent.config = config.replace(planner=config.planner.for_task(
        agent.task.cost_fn, agent.task.termination_fn))
    saved_map = StateMap.from_dict((saved_task or {}).get("state_map") or {})
    build_parts(agent, saved_map if saved_map.angles and agent.task.state_map.identity
                else agent.task.state_map)
    from agents.evaluation import Evaluator  # the oracle's map is the task's, found angles aside
    agent.evaluator = Evaluator(env, config, spec.episode_steps, cost_fn=agent.cost_fn,
                                state_map=agent.task.state_map,
                                terminal_cost_fn=agent.terminal_cost_fn,
                                termination_fn=agent.termination_fn)
    # the learning state (all of it goes into the checkpoint)
    agent.rng = np.random.default_rng(config.seed)
    # predict(deterministic=False)'s noise: its own stream, so acting leaves learning as is
    agent.predict_rng = np.random.default_rng((config.seed, 1))
    agent.trajectories = []
    agent.episodes_done = 0
    agent.env_steps = 0
    agent.logger_rows = []
    agent._log = None
    agent._rollout_steps = 0  # env steps of the running rollout (SB3 callbacks' count)
    agent._sb3_logger = None


def build_parts(agent: Any, state_map: StateMap) -> None:
    """Give ``agent`` (with ``env``, ``config``, ``spec``, ``task``) the cost, a fresh model and
    the parts on model state ``state_map`` (at construction and when angles are found)."""
    # the parts import this module (planning: LearnedTask), so they are imported here
    from agents.collection import Collector
    from agents.labels import JacobianLabeler, check_ltv_memory
    from agents.model_training import ModelTrainer
    from agents.planning import planner_cost
    from agents.tasks import ObservationCost
    from mbtsr.ensemble import DynamicsEnsemble

    env, config, spec = agent.env, agent.config, agent.spec
    agent.cost_fn, agent.state_map = agent.task.cost_fn, state_map
    agent.state_dim = state_dim = int(check_state_map(agent.state_map, env, spec).size)
    check_ltv_memory(config.regularization, state_dim, spec.act_dim)
    agent.terminal_cost_fn = agent.task.terminal_cost_fn
    if agent.cost_fn is None:
        agent.task_cost = LearnedTask(agent.state_map, spec, state_dim,
                                      dataclasses.replace(config.reward, seed=config.seed))
    else:
        agent.task_cost = ObservationCost(agent.cost_fn, agent.state_map, spec, state_dim,
                                          terminal_cost_fn=agent.terminal_cost_fn)
    agent.termination_fn = checked_termination_fn(agent.task.termination_fn, env, spec)
    agent.planner_cost = planner_cost(agent.task_cost, config.planner.terminal_weight)
    # the model: an ensemble of small networks, Objective 1 (f) or 2 (g)
    agent.ensemble_config = config.model.ensemble_config(state_dim, spec.act_dim, config.seed)
    agent.model = DynamicsEnsemble(agent.ensemble_config)
    # the parts
    agent.collector = Collector(env, spec, config.collection, agent.state_map)
    agent.labeler = JacobianLabeler(state_dim, spec.act_dim, config.regularization,
                                    config.ltv_prior)
    agent.trainer = ModelTrainer(agent.model, config.training, config.regularization,
                                 config.renormalize)
    agent.freeze()

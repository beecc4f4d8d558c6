"""Planner settings become an MPC policy in ONE place, :func:`make_policy` (docs/agent.md, "The
agent as parts"): :class:`MPCPolicy` (one solve per call, its state the rest of the plan),
:class:`TrueStatePolicy` (the oracle's, from a live MuJoCo env's true state) and
:class:`ReplanEvery` (each plan executed for ``replan_every`` steps). Values flow one way, from
the config into the built objects.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Callable
from typing import Any

import casadi as ca
import gymnasium as gym
import numpy as np

from agents.config import PlannerConfig
from agents.task_setup import LearnedTask
from agents.tasks import ObservationCost
from mbtsr.cem import cem
from mbtsr.cem_ilqr import CEMILQROptions, cem_ilqr
from mbtsr.costs import CasadiCost
from mbtsr.ilqr import ILQROptions, ilqr
from mbtsr.mpc import MPC, MPCOptions
from mbtsr.validation import as_array, check_callable, check_int

__all__ = ["MPCPolicy", "ReplanEvery", "ReplanState", "SB3Predictor", "TrueStatePolicy",
           "make_policy", "planner_cost", "solver"]


#: planner costs compile at their 50th call (the same bits 2-5x faster; short runs skip it)
JIT_AFTER = 50


def planner_cost(task_cost: ObservationCost | LearnedTask, terminal_weight: float = 1.0
                 ) -> CasadiCost:
    """The planner's :class:`mbtsr.costs.CasadiCost` of a task (a
    :class:`~agents.task_setup.LearnedTask`'s current reward), compiled once: stage
    ``cost_fn(obs_fn(s, p), a)`` and ``terminal_weight`` x the terminal cost on the model state
    ``s``, the reference observation ``p = obs [obs_dim]`` its parameter."""
    if isinstance(task_cost, LearnedTask):
        return task_cost.planner_cost(terminal_weight)
    n, m, d = task_cost.state_dim, task_cost.spec.act_dim, task_cost.spec.obs_dim
    s, a, p, t = ca.SX.sym("s", n), ca.SX.sym("a", m), ca.SX.sym("p", d), ca.SX.sym("t")
    stage = ca.Function("stage", [s, a, t, p], [task_cost.stage(s, a, p)])
    terminal = ca.Function(
        "terminal", [s, p], [float(terminal_weight) * task_cost.terminal(s, p)]
    )
    return CasadiCost(stage, terminal, n, m, jit=JIT_AFTER)


def solver(
    planner: PlannerConfig, seed: int = 0, *, explore_weight: float = 0.0,
    explore_on: str = "state", particles: int | None = None,
) -> tuple[Callable[..., Any], Any, int]:
    """``(optimizer, options, iterations per MPC step)`` of :class:`mbtsr.mpc.MPC` for ``planner``.

    :param seed: seeds CEM's samples (the agent's and the oracle's ``config.seed``).
    :param explore_weight: CEM's disagreement bonus (training rollouts; refused for iLQR).
    :param explore_on: what the bonus measures (``"state"`` or ``"cost"``).
    :param particles: replaces ``planner.cem.particles`` (``kind="cem"``; the oracle's 1).
    """
    explore = {"explore_weight": explore_weight, "explore_on": explore_on}
    if planner.kind == "ilqr":
        if explore_weight:
            raise ValueError("explore_weight needs a planner with CEM ('cem' or 'cem-ilqr'), "
                             "got planner.kind='ilqr'")
        return ilqr, ILQROptions(), planner.ilqr_iterations
    if planner.kind == "cem":
        options = dataclasses.replace(planner.cem, seed=seed, **explore, **(
            {} if particles is None else {"particles": particles}))
        return cem, options, options.iterations
    proposal = dataclasses.replace(planner.proposal, seed=seed, **explore)
    return (cem_ilqr, CEMILQROptions(max_iter=planner.ilqr_iterations, cem=proposal,
                                     warm_samples=planner.warm_samples),
            planner.ilqr_iterations)


def make_policy(
    planner: PlannerConfig,
    model: Any,
    task_cost: ObservationCost,
    *,
    seed: int = 0,
    cost: CasadiCost | None = None,
    termination_fn: Callable[[np.ndarray], np.ndarray] | None = None,
    explore_weight: float = 0.0,
    explore_on: str = "state",
    particles: int | None = None,
    true_state_env: gym.Env | None = None,
) -> ReplanEvery:
    """The agent's and the oracle's controller: ``MPC(solver(planner), cost, model,
    planner.horizon)`` in the action box, re-planned every ``planner.replan_every`` steps.

    :param planner: the planner settings (``None`` horizon, terminal weight: ``for_task``).
    :param model: a planning model (a frozen ensemble, a true model).
    :param task_cost: the task (cost, state maps, env spec).
    :param seed: see :func:`solver`.
    :param cost: the compiled :func:`planner_cost` to reuse (built when ``None``).
    :param termination_fn: see :class:`MPCPolicy`.
    :param explore_weight: / ``explore_on`` / ``particles``: see :func:`solver`.
    :param true_state_env: plan from this MuJoCo env's true state (:class:`TrueStatePolicy`).
    """
    planner = planner.for_task(getattr(task_cost, "cost_fn", None), termination_fn)
    optimizer, options, iterations = solver(planner, seed, explore_weight=explore_weight,
                                            explore_on=explore_on, particles=particles)
    spec = task_cost.spec
    if cost is None:
        cost = planner_cost(task_cost, planner.terminal_weight)
    mpc = MPC(
        optimizer, cost, model, planner.horizon, u_min=spec.u_min, u_max=spec.u_max,
        options=MPCOptions(
            iterations_per_step=iterations, first_step_iterations=planner.first_plan_iterations,
            optimizer_options=options, warm_start_lambda=False,
        ),
    )
    if true_state_env is None:
        policy = MPCPolicy(mpc, task_cost, planner.horizon, termination_fn)
    else:
        policy = TrueStatePolicy(mpc, task_cost, planner.horizon, true_state_env,
                                 termination_fn)
    return ReplanEvery(policy, planner.replan_every, planner.replan_feedback)


class SB3Predictor(abc.ABC):
    """Stable-Baselines3's ``predict`` over ``_act(observation, state)``: the MPC policies and
    the agent. A batch ``[B, obs_dim]`` is planned row by row, each row with its own recurrent
    state. ``episode_start`` forces a cold start (``state=None``); ``deterministic=False`` adds
    :meth:`_explore`'s noise (none for MPC; the agent's exploration noise)."""

    @abc.abstractmethod
    def _act(self, observation: Any, state: Any) -> tuple[np.ndarray, Any]:
        """One step from ``observation`` with the recurrent ``state`` (``None``: cold start)."""

    def predict(
        self,
        observation: np.ndarray,
        state: Any = None,
        episode_start: np.ndarray | bool | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, Any]:
        """One step (Stable-Baselines3 signature).

        :param observation: ``[obs_dim]``, or a batch ``[B, obs_dim]``.
        :param state: the recurrent state returned by the previous call (the remaining plan;
            for a batch, the list of the rows' states), or ``None`` (cold start).
        :param episode_start: ``True`` at the first step of an episode (for a batch ``[B]``
            flags, one per row): a cold start.
        :param deterministic: ``False`` adds the policy's exploration noise (:meth:`_explore`).
        :return: ``(action [m], next_state)``, for a batch ``(actions [B, m], [B] states)``.
        """
        obs = np.asarray(observation)
        if obs.ndim != 2:
            if episode_start is not None and bool(np.any(episode_start)):
                state = None
            action, state = self._act(observation, state)
            return (action if deterministic else self._explore(action)), state
        B = obs.shape[0]
        starts = np.asarray(False if episode_start is None else episode_start, dtype=bool)
        if starts.size not in (1, B):
            raise ValueError(f"for a batch of {B} observations, episode_start must be one flag "
                             f"or {B} flags, got {starts.size}")
        starts = np.broadcast_to(starts.reshape(-1), (B,))
        if state is None:
            state = [None] * B
        elif not isinstance(state, list | tuple) or len(state) != B:
            raise ValueError(f"for a batch of {B} observations, state must be the list of "
                             f"{B} states returned by predict (or None)")
        out = [self._act(obs[i], None if starts[i] else state[i]) for i in range(B)]
        actions = np.stack([a for a, _ in out])
        return (actions if deterministic else self._explore(actions)), [s for _, s in out]

    def _explore(self, action: np.ndarray) -> np.ndarray:
        """``action`` (``[m]`` or ``[B, m]``) with exploration noise, for
        ``deterministic=False``: unchanged here (MPC is deterministic)."""
        return action


class MPCPolicy(SB3Predictor):
    """Stable-Baselines3's ``predict`` for an :class:`mbtsr.mpc.MPC`: solves from the
    observation's model state (the observation the cost's parameter) and returns the first
    action with the rest of the plan, shifted, as the recurrent ``state`` ``[H, m]``.

    :param mpc: the controller (its cost from :func:`planner_cost`).
    :param task_cost: the task (observation/state maps, env spec).
    :param horizon: the plan length ``H`` (``planner.horizon``, the MPC's).
    :param termination_fn: ``obs [..., obs_dim] -> bool [...]`` (or ``None``): stage costs
        after a predicted termination are dropped (:func:`mbtsr.costs.truncated_total`).
    """

    def __init__(self, mpc: MPC, task_cost: ObservationCost, horizon: int,
                 termination_fn: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        if not isinstance(mpc, MPC):
            raise TypeError(f"mpc must be a mbtsr.mpc.MPC, got {type(mpc).__name__}")
        if termination_fn is not None:
            check_callable("termination_fn", termination_fn, "obs -> bool")
        self.mpc, self.horizon = mpc, int(horizon)
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
            if state.shape != (self.horizon, self.spec.act_dim):
                raise ValueError(
                    f"state must be the [H={self.horizon}, m={self.spec.act_dim}] plan "
                    f"returned by predict, got {list(state.shape)}"
                )
        res = self.mpc.solve(self.model_state(obs), 0, params=obs, warm_start=state,
                             **self._solve_kwargs(obs))
        self.last_result = res
        U = np.asarray(res.U, dtype=float)
        return np.clip(U[0], self.spec.u_min, self.spec.u_max), _shift(U)

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


class TrueStatePolicy(MPCPolicy):
    """:class:`MPCPolicy` that plans from the live ``env``'s TRUE state (``qpos, qvel``, mocap
    poses), lifted by an :class:`envs.mujoco_model.ObservedDynamics`: the oracle of a MuJoCo env.
    Only valid inside episodes of that ``env``."""

    def __init__(self, mpc: MPC, task_cost: ObservationCost, horizon: int, env: gym.Env,
                 termination_fn: Callable[[np.ndarray], np.ndarray] | None = None) -> None:
        super().__init__(mpc, task_cost, horizon, termination_fn)
        self.env = env

    def model_state(self, obs: np.ndarray) -> np.ndarray:
        from envs.mujoco_model import state_of

        dyn, base = self.model.dynamics, self.env.unwrapped
        if dyn.model.nmocap:
            dyn.set_mocap(base.data.mocap_pos, base.data.mocap_quat)
        return self.model.lift(state_of(self.env))


@dataclasses.dataclass(frozen=True)
class ReplanState:
    """The recurrent state of :class:`ReplanEvery` between two solves.

    :param plan: ``[H, m]`` the rest of the last plan (row 0 is played next).
    :param age: steps played since the last solve (``1 <= age``).
    :param states: ``[H, n]`` the last solve's predicted model states ``X_t`` for the plan's
        rows, or ``None`` (no feedback: open loop).
    :param gains: ``[H, m, n]`` iLQR's feedback gains ``K_t`` for the plan's rows, or ``None``.
    """

    plan: np.ndarray
    age: int
    states: np.ndarray | None = None
    gains: np.ndarray | None = None

    def shifted(self) -> ReplanState:
        """The state one step later: every array shifted by one row (the last repeated)."""
        return ReplanState(_shift(self.plan), self.age + 1, _shift(self.states),
                           _shift(self.gains))


def _shift(a: np.ndarray | None) -> np.ndarray | None:
    """``a`` one row later: ``a[1:]`` with the last row repeated (``None`` stays ``None``)."""
    return None if a is None else np.concatenate([a[1:], a[-1:]], axis=0)


class ReplanEvery(SB3Predictor):
    """Each plan of ``policy`` executed for ``k`` steps before the next solve; ``k = 1`` is
    ``policy`` itself (its state the plan ``[H, m]``), else the state is a :class:`ReplanState`.
    Between solves the controls ``U_t`` are played open loop or, with ``feedback``, through
    iLQR's local policy ``clip(U_t + K_t (x_t - X_t))`` (open loop without finite gains;
    docs/agent.md, the ``planner`` row of the defaults).

    :param policy: the :class:`MPCPolicy` re-solved every ``k`` steps.
    :param k: steps per plan (``planner.replan_every``).
    :param feedback: follow the local policy between solves (``planner.replan_feedback``).
    """

    def __init__(self, policy: MPCPolicy, k: int, feedback: bool = False) -> None:
        self.policy, self.k, self.feedback = policy, int(k), bool(feedback)

    def _act(self, observation: Any, state: Any) -> tuple[np.ndarray, Any]:
        if self.k == 1:
            return self.policy.predict(observation, state)
        if state is not None:
            self._check(state)
        if state is None or state.age >= self.k:
            action, rest = self.policy.predict(observation, None if state is None else state.plan)
            return action, ReplanState(rest, 1, *self._reference())
        spec = self.policy.spec
        obs = as_array("observation", observation, (spec.obs_dim,))
        u = state.plan[0]
        if state.gains is not None:
            corrected = u + state.gains[0] @ (self.policy.model_state(obs) - state.states[0])
            if np.all(np.isfinite(corrected)):
                u = corrected
        return np.clip(u, spec.u_min, spec.u_max), state.shifted()

    def _check(self, state: Any) -> None:
        """Refuse a state that is not a :class:`ReplanState` of this policy's sizes."""
        if not isinstance(state, ReplanState):
            raise ValueError(f"state must be the ReplanState the previous call returned, got "
                             f"{type(state).__name__}")
        H, m = self.policy.horizon, self.policy.spec.act_dim
        if np.shape(state.plan) != (H, m) or not np.all(np.isfinite(state.plan)):
            raise ValueError(f"state.plan must be a finite [H={H}, m={m}] plan, got shape "
                             f"{list(np.shape(state.plan))}")
        check_int("state.age", state.age, 1)

    def _reference(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(states [H, n], gains [H, m, n])`` of the last solve for the steps after the first
        (shifted as the plan); ``(None, None)`` (open loop) without ``feedback`` or finite gains."""
        res = self.policy.last_result
        K = getattr(res, "K", None)
        if not self.feedback or K is None:
            return None, None
        X = np.asarray(res.X, dtype=float)
        H, n, m = X.shape[0] - 1, X.shape[1], self.policy.spec.act_dim
        K = np.asarray(K, dtype=float).reshape(H, m, n)
        if not (np.all(np.isfinite(X)) and np.all(np.isfinite(K))):
            return None, None
        return X[1:], _shift(K)

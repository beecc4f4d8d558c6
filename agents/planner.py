"""Receding-horizon iLQR (MPC) on any dynamics model, with the SB3 ``predict`` surface.

At every step the policy solves ``min_U sum_{k<H} l(s_k, u_k) + l_T(s_H)`` from the current model
state with :func:`mbtsr.ilqr.ilqr` on the model's Jacobians, applies the first action and keeps
the rest of the plan, shifted by one step, as the warm start of the next solve. The warm start is
the recurrent ``state`` of :meth:`MPCPolicy.predict`, so ``predict`` is a pure function of its
arguments (same inputs, same action) -- the same controller serves the agent (learned model) and
the oracle (true model).
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

import casadi as ca
import numpy as np

from agents.task import EnvSpec, ObservationCost
from mbtsr.costs import CasadiCost
from mbtsr.dynamics import DynamicsModel
from mbtsr.ilqr import ilqr
from mbtsr.validation import as_array, check_finite

__all__ = ["MPCPolicy", "PlannerCosts"]


class PlannerCosts:
    """:class:`mbtsr.costs.CasadiCost` objects for the planner, one per reference context.

    The state cost ``cost_fn(obs_fn(s, obs_ref), a)`` depends on the reference observation only
    through the entries it actually uses (for the arm: the target); those entries are found
    symbolically once, and costs are cached by their values (LRU), so a new cost is compiled
    only when, e.g., the target changes.

    :param task_cost: the compiled observation cost.
    :param terminal_weight: terminal cost = weight x stage cost at zero action.
    :param cache_size: number of cached contexts.
    """

    def __init__(
        self, task_cost: ObservationCost, terminal_weight: float = 1.0, cache_size: int = 32
    ) -> None:
        self.task_cost = task_cost
        self.terminal_weight = float(terminal_weight)
        n, m, d = task_cost.state_dim, task_cost.spec.act_dim, task_cost.spec.obs_dim
        s, a, p = ca.SX.sym("s", n), ca.SX.sym("a", m), ca.SX.sym("p", d)
        t = ca.SX.sym("t")
        expr = task_cost.stage(s, a, p)
        # which entries of obs_ref does the planner's cost really depend on?
        self.context_index = np.array(
            [i for i in range(d) if ca.depends_on(expr, p[i])], dtype=np.int64
        )
        self._stage = ca.Function("stage", [s, a, t, p], [expr])
        self._terminal = ca.Function(
            "terminal", [s, p], [self.terminal_weight * task_cost.terminal(s, p)]
        )
        self._n, self._m = n, m
        self._cache: OrderedDict[bytes, CasadiCost] = OrderedDict()
        self._cache_size = int(cache_size)

    def context(self, obs_ref: np.ndarray) -> np.ndarray:
        """The entries of ``obs_ref`` the cost depends on."""
        return np.asarray(obs_ref, dtype=float)[self.context_index]

    def __call__(self, obs_ref: np.ndarray) -> CasadiCost:
        """The planner cost for the reference observation ``obs_ref: [obs_dim]``."""
        obs_ref = np.asarray(obs_ref, dtype=float)
        key = self.context(obs_ref).tobytes()
        cost = self._cache.get(key)
        if cost is None:
            params = np.zeros((1, obs_ref.shape[0]))
            params[0, self.context_index] = obs_ref[self.context_index]
            cost = CasadiCost(self._stage, self._terminal, self._n, self._m, params=params)
            self._cache[key] = cost
            if len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(key)
        return cost


class MPCPolicy:
    """MPC with iLQR on ``model``: ``predict(obs, state) -> (action, state)``.

    :param model: any :class:`mbtsr.dynamics.DynamicsModel` on the model state.
    :param costs: the planner costs (see :class:`PlannerCosts`).
    :param spec: the env's spec (action bounds).
    :param horizon: MPC horizon ``H`` (steps).
    :param iterations: iLQR iterations per step when warm-started.
    :param first_plan_iterations: iLQR iterations of a cold start (new episode).
    :param ilqr_options: extra options for :func:`mbtsr.ilqr.ilqr`.
    """

    def __init__(
        self,
        model: DynamicsModel,
        costs: PlannerCosts,
        spec: EnvSpec,
        *,
        horizon: int,
        iterations: int,
        first_plan_iterations: int,
        ilqr_options: dict[str, Any] | None = None,
    ) -> None:
        self.model = model
        self.costs = costs
        self.spec = spec
        self.state_map = costs.task_cost.state_map
        self.horizon = int(horizon)
        self.iterations = int(iterations)
        self.first_plan_iterations = int(first_plan_iterations)
        self.ilqr_options = dict(ilqr_options or {})
        self.last_result = None

    def initial_plan(self) -> np.ndarray:
        """Cold-start controls ``[H, m]``: the middle of the action box."""
        mid = 0.5 * (self.spec.u_min + self.spec.u_max)
        return np.tile(mid, (self.horizon, 1))

    def plan(self, obs: np.ndarray, U0: np.ndarray | None = None) -> tuple[np.ndarray, Any]:
        """Optimise the controls ``[H, m]`` from observation ``obs`` (warm start ``U0``)."""
        s = self.state_map.state(obs)
        cold = U0 is None
        U0 = self.initial_plan() if cold else U0
        iters = self.first_plan_iterations if cold else self.iterations
        res = ilqr(
            self.costs(obs),
            self.model,
            s,
            U0,
            u_min=self.spec.u_min,
            u_max=self.spec.u_max,
            options={**self.ilqr_options, "max_iter": iters},
        )
        self.last_result = res
        return np.asarray(res.U, dtype=float), res

    def predict(
        self,
        observation: np.ndarray,
        state: np.ndarray | None = None,
        episode_start: np.ndarray | bool | None = None,
        deterministic: bool = True,
    ) -> tuple[np.ndarray, np.ndarray]:
        """One MPC step (Stable-Baselines3 signature).

        :param observation: ``[obs_dim]`` current observation.
        :param state: ``[H, m]`` warm start returned by the previous call, or ``None`` (cold
            start, also forced by ``episode_start``).
        :param episode_start: ``True`` at the first step of an episode.
        :param deterministic: unused (MPC is deterministic); kept for SB3 compatibility.
        :return: ``(action [m], next_state [H, m])``.
        """
        obs = as_array("observation", observation, finite=False)  # refuses complex values
        if obs.shape != (self.spec.obs_dim,):
            raise ValueError(
                f"observation must have shape ({self.spec.obs_dim},), got {list(obs.shape)}"
            )
        check_finite("observation", obs)
        if episode_start is not None and bool(np.any(episode_start)):
            state = None
        if state is not None:
            state = np.asarray(state, dtype=float)
            if state.shape != (self.horizon, self.spec.act_dim):
                raise ValueError(
                    f"state must be the [H={self.horizon}, m={self.spec.act_dim}] plan returned "
                    f"by predict, got {list(state.shape)}"
                )
        U, _ = self.plan(obs, state)
        action = np.clip(U[0], self.spec.u_min, self.spec.u_max)
        next_state = np.concatenate([U[1:], U[-1:]], axis=0)
        return action, next_state

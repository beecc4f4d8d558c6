"""Receding-horizon control (MPC) with iLQR on any dynamics model.

At every control step ``t`` the controller solves the finite-horizon problem ::

    min_U  sum_{k=0}^{H-1} l(x_k, u_k, t + k) + l_T(x_H),   x_0 = current state

with a few iLQR iterations (:func:`mbtsr.ilqr.ilqr`), warm-started from the previous plan
shifted by the elapsed steps (the last control repeated at the end) and from the previous
regularisation, and applies the first control. The cost receives the absolute time ``t + k``,
so time-indexed references (:func:`mbtsr.costs.quadratic_cost` with ``x_goal: [N, n]``) are
followed in step with the environment.

:func:`run_mpc_episode` drives any Gymnasium env with an :class:`MPC` and records states,
actions, rewards and the compute time per control step.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from mbtsr.costs import CasadiCost
from mbtsr.ilqr import ILQROptions, ILQRResult, check_control_bounds, ilqr
from mbtsr.validation import as_array

__all__ = ["MPC", "MPCOptions", "run_mpc_episode"]


@dataclass(frozen=True)
class MPCOptions:
    """Settings of :class:`MPC`.

    :param iterations_per_step: iLQR iterations per control step when warm-started.
    :param first_step_iterations: iLQR iterations of a cold start (first step, after
        :meth:`MPC.reset`, or when the warm start is unusable).
    :param ilqr: options of the inner solver (``max_iter`` is overridden by the two above).
    :param warm_start_lambda: start each solve from the previous solve's regularisation,
        capped at ``ilqr.lambda_init`` (instead of ``lambda_init`` every time).
    """

    iterations_per_step: int = 3
    first_step_iterations: int = 50
    ilqr: ILQROptions = field(default_factory=lambda: ILQROptions(tol_fun_rel=1e-6))
    warm_start_lambda: bool = True

    def __post_init__(self) -> None:
        for name in ("iterations_per_step", "first_step_iterations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")
        if not isinstance(self.ilqr, ILQROptions):
            raise TypeError(f"ilqr must be an ILQROptions, got {type(self.ilqr).__name__}")


class MPC:
    """Receding-horizon iLQR controller.

    :param cost: the task cost (:class:`mbtsr.costs.CasadiCost`), evaluated at absolute times.
    :param dynamics: any model with the :class:`mbtsr.dynamics.DynamicsModel` protocol.
    :param horizon: planning horizon ``H`` in steps.
    :param u_min: ``[m]`` (or scalar) lower control bound, ``None`` = unbounded.
    :param u_max: ``[m]`` (or scalar) upper control bound, ``None`` = unbounded.
    :param options: :class:`MPCOptions`.
    :param U_init: ``[H, m]`` cold-start plan; default: the middle of the box (0 if unbounded).

    Attributes: ``compute_times`` (seconds per :meth:`act` call since the last reset),
    ``last_result`` (the last :class:`mbtsr.ilqr.ILQRResult`), ``plan`` (current ``[H, m]``
    plan or ``None``).
    """

    def __init__(
        self,
        cost: CasadiCost,
        dynamics,
        horizon: int = 50,
        u_min: np.ndarray | float | None = None,
        u_max: np.ndarray | float | None = None,
        options: MPCOptions | None = None,
        U_init: np.ndarray | None = None,
    ) -> None:
        if not isinstance(cost, CasadiCost):
            raise TypeError(f"cost must be a mbtsr.costs.CasadiCost, got {type(cost).__name__}")
        if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or horizon < 1:
            raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
        self.options = MPCOptions() if options is None else options
        if not isinstance(self.options, MPCOptions):
            raise TypeError(f"options must be an MPCOptions, got {type(self.options).__name__}")
        n, m = cost.n, cost.m
        for attr, want in (("state_dim", n), ("action_dim", m)):
            got = getattr(dynamics, attr, want)
            if got != want:
                raise ValueError(
                    f"dynamics.{attr}={got} does not match the cost's dimension {want}"
                )
        self.cost, self.dynamics, self.horizon = cost, dynamics, int(horizon)
        self.u_min, self.u_max = check_control_bounds(u_min, u_max, m)
        if U_init is None:
            bounded = np.isfinite(self.u_min) & np.isfinite(self.u_max)
            middle = np.clip(np.zeros(m), self.u_min, self.u_max)
            middle[bounded] = 0.5 * (self.u_min[bounded] + self.u_max[bounded])
            U_init = np.tile(middle, (self.horizon, 1))
        self.U_init = np.clip(as_array("U_init", U_init, (self.horizon, m)), self.u_min, self.u_max)
        self.reset()

    def reset(self) -> None:
        """Forget the warm start and the recorded compute times (call at a new episode)."""
        self.plan: np.ndarray | None = None
        self.compute_times: list[float] = []
        self.last_result: ILQRResult | None = None
        self._t_plan: int | None = None
        self._lam: float | None = None

    def act(self, x: np.ndarray, t: int = 0) -> np.ndarray:
        """The control to apply now.

        :param x: ``[n]`` current state.
        :param t: absolute time index of ``x`` (the cost sees ``t + k`` along the horizon).
        :return: ``[m]`` control within the bounds.
        """
        tic = time.perf_counter()
        x = as_array("x", x, (self.cost.n,))
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or t < 0:
            raise ValueError(f"t must be an integer time index >= 0, got {t!r}")
        t = int(t)
        shift = None if self._t_plan is None else t - self._t_plan
        if self.plan is None or shift is None or not 0 <= shift < self.horizon:
            U0, iters, lam = self.U_init, self.options.first_step_iterations, None
        else:
            U0 = np.concatenate([self.plan[shift:], np.repeat(self.plan[-1:], shift, axis=0)])
            iters, lam = self.options.iterations_per_step, self._lam
        opts = replace(self.options.ilqr, max_iter=iters)
        if lam is not None and self.options.warm_start_lambda:
            opts = replace(opts, lambda_init=min(lam, self.options.ilqr.lambda_init))
        res = ilqr(
            self.cost, self.dynamics, x, U0, u_min=self.u_min, u_max=self.u_max, options=opts, t0=t
        )
        self.plan, self._t_plan, self._lam, self.last_result = res.U, t, res.lam, res
        action = res.U[0].copy()
        self.compute_times.append(time.perf_counter() - tic)
        return action


def run_mpc_episode(
    env,
    mpc: MPC,
    state_fn: Callable[[np.ndarray, dict], np.ndarray] = lambda obs, info: info["state"],
    seed: int | None = None,
    options: dict | None = None,
    max_steps: int | None = None,
) -> dict:
    """Run one episode of ``env`` under ``mpc`` (any Gymnasium env; no ``envs`` import).

    :param env: a Gymnasium env whose actions are the controls ``mpc`` plans.
    :param mpc: the controller; it is reset first.
    :param state_fn: ``(obs, info) -> x [n]`` the model state (default ``info["state"]``).
    :param seed: passed to ``env.reset``.
    :param options: passed to ``env.reset`` (e.g. ``{"target": ..., "state": ...}``).
    :param max_steps: stop after this many steps (default: until terminated/truncated).
    :return: dict with ``states [T+1, n]``, ``actions [T, m]``, ``rewards [T]``,
        ``compute_times [T]`` (seconds per control step), ``total_reward``, ``steps``,
        ``terminated``, ``truncated``, ``ilqr_status`` (one per step), ``info`` (the last info).
    """
    if max_steps is not None and (int(max_steps) != max_steps or max_steps < 1):
        raise ValueError(f"max_steps must be an integer >= 1 or None, got {max_steps!r}")
    mpc.reset()
    obs, info = env.reset(seed=seed, options=options)
    states = [np.asarray(state_fn(obs, info), dtype=float)]
    actions, rewards, statuses = [], [], []
    terminated = truncated = False
    t = 0
    while True:
        a = mpc.act(states[-1], t)
        obs, reward, terminated, truncated, info = env.step(a)
        actions.append(a)
        rewards.append(float(reward))
        statuses.append(mpc.last_result.status)
        states.append(np.asarray(state_fn(obs, info), dtype=float))
        t += 1
        if terminated or truncated or (max_steps is not None and t >= max_steps):
            break
    return {
        "states": np.stack(states),
        "actions": np.stack(actions),
        "rewards": np.asarray(rewards),
        "compute_times": np.asarray(mpc.compute_times),
        "total_reward": float(np.sum(rewards)),
        "steps": t,
        "terminated": bool(terminated),
        "truncated": bool(truncated),
        "ilqr_status": statuses,
        "info": info,
    }

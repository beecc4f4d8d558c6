"""Receding-horizon control (MPC) with any trajectory optimizer on any planning model.

Every control step solves from the current state with a few iterations of the optimizer (the
shared signature of :func:`mbtsr.ilqr.ilqr`), warm-started from the previous plan shifted by the
elapsed steps, and applies the first control. The manual: docs/ilqr.md, "MPC".
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from mbtsr.cem import CEMOptions, cem
from mbtsr.cem_ilqr import CEMILQROptions, cem_ilqr
from mbtsr.costs import CasadiCost
from mbtsr.dynamics import check_planning_model
from mbtsr.ilqr import ILQROptions, check_control_bounds, ilqr
from mbtsr.validation import as_array, check_int, options_from

__all__ = ["MPC", "MPCOptions"]


@dataclass(frozen=True)
class MPCOptions:
    """Settings of :class:`MPC`.

    :param iterations_per_step: optimizer iterations per control step when warm-started.
    :param first_step_iterations: iterations of a cold start (first step, after
        :meth:`MPC.reset`, or when the warm start is unusable).
    :param optimizer_options: options of the optimizer (an :class:`mbtsr.ilqr.ILQROptions`,
        a :class:`mbtsr.cem.CEMOptions` or a dict of their fields); the iteration cap
        (``max_iter`` / ``iterations``) is overridden by the two counts above. ``None``: the
        optimizer's defaults (for iLQR ``ILQROptions()``, as the agent's planner uses).
    :param warm_start_lambda: (iLQR) start each solve from the previous solve's regularisation,
        capped at ``lambda_init`` (instead of ``lambda_init`` every time).
    :param cold_start_fractions: a cold start first solves these fractions of the horizon, in
        order, each warm-started from the previous solve's plan extended by its last control,
        then the whole horizon (each with ``first_step_iterations``; why: docs/ilqr.md, "MPC").
        ``()``: no continuation.
    """

    iterations_per_step: int = 3
    first_step_iterations: int = 50
    optimizer_options: Any = None
    warm_start_lambda: bool = True
    cold_start_fractions: tuple[float, ...] = (0.25, 0.5)

    def __post_init__(self) -> None:
        for name in ("iterations_per_step", "first_step_iterations"):
            check_int(name, getattr(self, name), 1)
        fr = tuple(float(f) for f in self.cold_start_fractions)
        if any(not 0.0 < f < 1.0 for f in fr) or list(fr) != sorted(fr):
            raise ValueError(f"cold_start_fractions must be increasing numbers in (0, 1), got "
                             f"{self.cold_start_fractions!r}")
        object.__setattr__(self, "cold_start_fractions", fr)
        o = self.optimizer_options
        if not (o is None or isinstance(o, Mapping) or dataclasses.is_dataclass(o)):
            raise TypeError(
                f"optimizer_options must be None, a dict or an options dataclass, got "
                f"{type(o).__name__}"
            )


class MPC:
    """Receding-horizon controller: ``MPC(optimizer, cost, model, horizon)``.

    :param optimizer: a trajectory optimizer with the shared signature (docs/ilqr.md, "MPC"),
        e.g. :func:`mbtsr.ilqr.ilqr` or ``mbtsr.cem.cem``.
    :param cost: the task cost (:class:`mbtsr.costs.CasadiCost`), evaluated at absolute times.
    :param model: a planning model (:mod:`mbtsr.dynamics` protocol; a learned ensemble's
        ``freeze()``).
    :param horizon: planning horizon ``H`` in steps.
    :param u_min: ``[m]`` (or scalar) lower control bound, ``None`` = unbounded.
    :param u_max: ``[m]`` (or scalar) upper control bound, ``None`` = unbounded.
    :param options: :class:`MPCOptions` (or a dict of its fields).
    :param U_init: ``[H, m]`` cold-start plan; default: the middle of the box (0 if unbounded).
    :param params: default cost parameters (``[p]`` or ``[N_ref, p]``) when a call gives none.

    Attributes: ``compute_times`` and ``statuses`` (per :meth:`act` since the last
    :meth:`reset`), ``last_result`` (the optimizer's last result), ``plan`` (current ``[H, m]``
    plan or ``None``).
    """

    def __init__(
        self,
        optimizer: Callable[..., Any],
        cost: CasadiCost,
        model: Any,
        horizon: int = 50,
        *,
        u_min: np.ndarray | float | None = None,
        u_max: np.ndarray | float | None = None,
        options: MPCOptions | None = None,
        U_init: np.ndarray | None = None,
        params: np.ndarray | None = None,
    ) -> None:
        if not callable(optimizer):
            raise TypeError(f"optimizer must be callable, got {type(optimizer).__name__}")
        if not isinstance(cost, CasadiCost):
            raise TypeError(f"cost must be a mbtsr.costs.CasadiCost, got {type(cost).__name__}")
        check_int("horizon", horizon, 1)
        self.options = options_from(MPCOptions, options)
        n, m = cost.n, cost.m
        check_planning_model(model, n, m)
        self.optimizer, self.cost, self.model, self.horizon = optimizer, cost, model, int(horizon)
        self.u_min, self.u_max = check_control_bounds(u_min, u_max, m)
        self.params = None if params is None else cost.check_params(params)
        if U_init is None:
            bounded = np.isfinite(self.u_min) & np.isfinite(self.u_max)
            middle = np.clip(np.zeros(m), self.u_min, self.u_max)
            middle[bounded] = 0.5 * (self.u_min[bounded] + self.u_max[bounded])
            U_init = np.tile(middle, (self.horizon, 1))
        self.U_init = np.clip(as_array("U_init", U_init, (self.horizon, m)), self.u_min, self.u_max)
        self._base_options = _resolve_options(optimizer, self.options.optimizer_options)
        self.reset()

    def reset(self) -> None:
        """Forget the warm start and the recorded times/statuses (a new episode)."""
        self.plan: np.ndarray | None = None
        self.compute_times: list[float] = []
        self.statuses: list[str] = []
        self.last_result: Any = None
        self._t_plan: int | None = None
        self._lam: float | None = None

    def _options(self, iterations: int, lam: float | None, cold: bool = False) -> Any:
        """The optimizer's options with its iteration cap (iLQR ``max_iter``, CEM
        ``iterations``) and iLQR's ``lambda_init`` set; for a cold start, options that offer
        ``for_cold_start()`` (:class:`mbtsr.cem_ilqr.CEMILQROptions`) give theirs."""
        base = self._base_options
        if cold and hasattr(base, "for_cold_start"):
            base = base.for_cold_start()
        iterations_only = dataclasses.is_dataclass(base) and not hasattr(base, "max_iter")
        extra: dict[str, Any] = {"iterations" if iterations_only else "max_iter": int(iterations)}
        if lam is not None:
            init = base.get("lambda_init") if isinstance(base, Mapping) else getattr(
                base, "lambda_init", None)
            extra["lambda_init"] = min(lam, ILQROptions.lambda_init if init is None else init)
        if isinstance(base, Mapping):
            return {**base, **extra}
        return dataclasses.replace(base, **extra)

    def solve(
        self,
        x: np.ndarray,
        t: int = 0,
        *,
        params: np.ndarray | None = None,
        warm_start: np.ndarray | None = None,
        **optimizer_kwargs: Any,
    ) -> Any:
        """One solve from state ``x`` at time ``t`` (no controller state is read or written).

        :param warm_start: ``[H, m]`` plan to start from (``options.iterations_per_step``
            iterations); ``None``: a cold start from ``U_init`` (``first_step_iterations``).
        :param optimizer_kwargs: extra keyword arguments of the optimizer (e.g. CEM's
            ``terminated``).
        :return: the optimizer's result.
        """
        x = as_array("x", x, (self.cost.n,))
        t = check_int("t", t, 0)
        if warm_start is None:
            return self._cold_solve(x, t, params, optimizer_kwargs)
        U0 = np.clip(as_array("warm_start", warm_start, (self.horizon, self.cost.m)),
                     self.u_min, self.u_max)
        return self._solve(x, t, params, U0, self.options.iterations_per_step, None,
                           optimizer_kwargs)

    def _solve(self, x, t, params, U0, iterations, lam, kwargs=None, cold=False) -> Any:
        return self.optimizer(
            self.cost, self.model, x, U0, u_min=self.u_min, u_max=self.u_max,
            params=self.params if params is None else params, t0=t,
            options=self._options(iterations, lam, cold), **(kwargs or {}),
        )

    def _cold_solve(self, x, t, params, kwargs=None) -> Any:
        """A cold start from ``U_init``, through the horizons of ``cold_start_fractions``
        (see :class:`MPCOptions`); the last solve is over the whole horizon."""
        H, its = self.horizon, self.options.first_step_iterations
        lengths = sorted({max(1, round(f * H)) for f in self.options.cold_start_fractions} - {H})
        U = self.U_init[: lengths[0]] if lengths else self.U_init
        for h in [*lengths, H]:
            U0 = np.concatenate([U, np.repeat(U[-1:], h - len(U), axis=0)])
            res = self._solve(x, t, params, U0, its, None, kwargs, cold=True)
            U = res.U
        return res

    def act(self, x: np.ndarray, t: int = 0, params: np.ndarray | None = None) -> np.ndarray:
        """The control to apply now (warm-started from the previous call's plan).

        :param x: ``[n]`` current state.
        :param t: absolute time index of ``x`` (the cost sees ``t + k`` along the horizon).
        :param params: cost parameters (default: the controller's ``params``).
        :return: ``[m]`` control within the bounds (finite even when the solve failed: the
            optimizer returns its best finite iterate).
        """
        tic = time.perf_counter()
        x = as_array("x", x, (self.cost.n,))
        t = check_int("t", t, 0)
        if self.plan is None or not 0 <= t - self._t_plan < self.horizon:
            res = self._cold_solve(x, t, params)
        else:
            shift = t - self._t_plan
            U0 = np.concatenate([self.plan[shift:], np.repeat(self.plan[-1:], shift, axis=0)])
            lam = self._lam if self.options.warm_start_lambda else None
            res = self._solve(x, t, params, U0, self.options.iterations_per_step, lam)
        self.plan, self._t_plan, self.last_result = res.U, t, res
        self._lam = getattr(res, "lam", None)
        self.statuses.append(res.status)
        action = np.array(res.U[0], dtype=float)
        self.compute_times.append(time.perf_counter() - tic)
        return action

    __call__ = act


def _resolve_options(optimizer: Callable[..., Any], options: Any) -> Any:
    """The optimizer's base options: iLQR's and CEM's as their options dataclasses (a dict is
    checked here, once), other optimizers' as given (``None``: a dict)."""
    for solver, cls in ((ilqr, ILQROptions), (cem, CEMOptions), (cem_ilqr, CEMILQROptions)):
        if optimizer is solver:
            return options_from(cls, options)
    return {} if options is None else options

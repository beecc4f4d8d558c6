"""IPOPT reference solution of the optimal-control problem iLQR solves: direct multiple shooting
with CasADi ``Opti`` on the model's one-step CasADi function and the same
:class:`mbtsr.costs.CasadiCost`, exact Hessian (docs/ilqr.md, "IPOPT reference").
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from mbtsr.costs import CasadiCost
from mbtsr.ilqr import check_control_bounds
from mbtsr.validation import as_array, check_int

__all__ = ["IpoptResult", "solve_ipopt"]


@dataclass(frozen=True)
class IpoptResult:
    """Outcome of :func:`solve_ipopt`.

    :param X: ``[T+1, n]`` optimal states (IPOPT's multiple-shooting variables).
    :param U: ``[T, m]`` optimal controls.
    :param cost: ``cost.total(X_sim, U)`` where ``X_sim`` re-simulates ``U`` through ``F`` from
        ``x0`` (equal to the objective up to the constraint tolerance).
    :param wall_time: seconds inside ``Opti.solve`` (problem construction excluded).
    :param build_time: seconds to build the ``Opti`` problem.
    :param iterations: IPOPT iterations.
    :param status: IPOPT's return status (e.g. ``"Solve_Succeeded"``).
    :param success: whether IPOPT reported success.
    :param X_sim: ``[T+1, n]`` simulation of ``U`` through ``F``.
    """

    X: np.ndarray
    U: np.ndarray
    cost: float
    wall_time: float
    build_time: float
    iterations: int
    status: str
    success: bool
    X_sim: np.ndarray = field(repr=False)


def solve_ipopt(
    casadi_step: ca.Function,
    cost: CasadiCost,
    x0: np.ndarray,
    T: int,
    u_min: np.ndarray | float | None,
    u_max: np.ndarray | float | None,
    U0: np.ndarray | None = None,
    *,
    t0: int = 0,
    params: np.ndarray | None = None,
    max_iter: int = 3000,
    tol: float = 1e-8,
    ipopt_options: dict | None = None,
) -> IpoptResult:
    """Solve ``min_U J(X, U)`` s.t. ``x_{t+1} = F(x_t, u_t)``, ``x_0 = x0``, box bounds on ``u``.

    :param casadi_step: ``casadi.Function`` ``F(x[n], u[m]) -> x_next[n]`` (one model step).
    :param cost: the :class:`mbtsr.costs.CasadiCost` iLQR uses.
    :param x0: ``[n]`` initial state.
    :param T: horizon (number of controls).
    :param u_min: ``[m]``/scalar lower bound or ``None``.
    :param u_max: ``[m]``/scalar upper bound or ``None``.
    :param U0: ``[T, m]`` initial guess of the controls (default zeros, clipped to the bounds);
        the state guess is its simulation through ``F``.
    :param t0: absolute time of ``x0`` (for time-indexed costs).
    :param params: cost parameters (``[p]`` or ``[N_ref, p]``; default: the cost's own), as
        for :func:`mbtsr.ilqr.ilqr`.
    :param max_iter: IPOPT iteration cap.
    :param tol: IPOPT convergence tolerance.
    :param ipopt_options: extra IPOPT options (override the defaults above).
    :return: :class:`IpoptResult`.
    """
    if not isinstance(casadi_step, ca.Function):
        raise TypeError(f"casadi_step must be a casadi.Function, got {type(casadi_step).__name__}")
    if not isinstance(cost, CasadiCost):
        raise TypeError(f"cost must be a mbtsr.costs.CasadiCost, got {type(cost).__name__}")
    n, m = cost.n, cost.m
    if (
        casadi_step.n_in() != 2
        or tuple(casadi_step.size_in(0)) != (n, 1)
        or tuple(casadi_step.size_in(1)) != (m, 1)
        or tuple(casadi_step.size_out(0)) != (n, 1)
    ):
        raise ValueError(
            f"casadi_step must map (x[{n}], u[{m}]) -> x_next[{n}] like the cost; got inputs "
            f"{[tuple(casadi_step.size_in(i)) for i in range(casadi_step.n_in())]}"
        )
    T, t0 = check_int("T", T, 1), check_int("t0", t0, 0)
    x0 = as_array("x0", x0, (n,))
    lower, upper = check_control_bounds(u_min, u_max, m)
    U0 = np.zeros((T, m)) if U0 is None else as_array("U0", U0, (T, m))
    U0 = np.clip(U0, lower, upper)

    tic = time.perf_counter()
    step_T = casadi_step.map(T)
    X0 = _simulate(casadi_step, x0, U0)
    opti = ca.Opti()
    X = opti.variable(n, T + 1)
    U = opti.variable(m, T)
    opti.subject_to(X[:, 0] == x0)
    opti.subject_to(X[:, 1:] == step_T(X[:, :-1], U))
    if np.any(np.isfinite(lower)) or np.any(np.isfinite(upper)):
        opti.subject_to(
            opti.bounded(np.tile(lower[:, None], (1, T)), U, np.tile(upper[:, None], (1, T)))
        )
    times = np.arange(t0, t0 + T + 1)
    P = cost.params_at(times, params)
    stage = cost.stage.map(T)(X[:, :-1], U, times[None, :-1].astype(float), P[:-1].T)
    opti.minimize(ca.sum2(stage) + cost.terminal(X[:, -1], P[-1]))
    opti.set_initial(X, X0.T)
    opti.set_initial(U, U0.T)
    options = {"print_level": 0, "sb": "yes", "max_iter": int(max_iter), "tol": float(tol)}
    options.update(ipopt_options or {})
    opti.solver("ipopt", {"print_time": False}, options)
    build_time = time.perf_counter() - tic

    tic = time.perf_counter()
    try:
        sol = opti.solve()
        value = sol.value
    except RuntimeError:  # IPOPT did not succeed: report its last iterate
        value = opti.debug.value
    wall_time = time.perf_counter() - tic
    stats = opti.stats()
    X_opt = np.atleast_2d(np.asarray(value(X), dtype=float)).reshape(n, T + 1).T
    U_opt = np.clip(np.asarray(value(U), dtype=float).reshape(m, T).T, lower, upper)
    X_sim = _simulate(casadi_step, x0, U_opt)
    J = float(cost.total(X_sim, U_opt, t0, params)) if np.all(np.isfinite(X_sim)) else float("inf")
    return IpoptResult(
        X=X_opt,
        U=U_opt,
        cost=J,
        wall_time=wall_time,
        build_time=build_time,
        iterations=int(stats.get("iter_count", -1)),
        status=str(stats.get("return_status", "")),
        success=bool(stats.get("success", False)),
        X_sim=X_sim,
    )


def _simulate(step: ca.Function, x0: np.ndarray, U: np.ndarray) -> np.ndarray:
    """Roll ``U [T, m]`` through ``step`` from ``x0`` -> ``[T+1, n]`` (NaN after divergence)."""
    X = np.full((U.shape[0] + 1, x0.shape[0]), np.nan)
    X[0] = x0
    for t in range(U.shape[0]):
        X[t + 1] = np.asarray(step(X[t], U[t])).ravel()
        if not np.all(np.isfinite(X[t + 1])):
            X[t + 1 :] = np.nan
            break
    return X

"""Cross-entropy method (CEM) trajectory optimisation, the sampling planner of PETS.

Only the model's batched forward predictions, never its Jacobians; same signature as
:func:`mbtsr.ilqr.ilqr`; same seed, same result. The algorithm step by step: docs/ilqr.md, "CEM".
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mbtsr.costs import after_termination, terminations, truncated_total
from mbtsr.dynamics import _rollout
from mbtsr.ilqr import check_problem
from mbtsr.validation import check_choice, check_int, options_from

__all__ = ["CEMOptions", "CEMResult", "cem"]


@dataclass(frozen=True)
class CEMOptions:
    """Settings of :func:`cem`.

    :param samples: action sequences sampled per iteration (PETS: 400-500).
    :param elites: lowest-cost samples that refit the Gaussian (PETS: 40-50).
    :param iterations: iteration cap (PETS: 5).
    :param init_std: initial per-dimension std as a fraction of the half-range of the bounds.
    :param smoothing: weight ``a`` of the previous mean/std in the update (PETS: 0.1).
    :param tol_std: converged when every std is below this fraction of the half-range.
    :param seed: seed of the samples (an int; same seed, same result).
    :param max_state_norm: a rollout whose ``max |x|`` exceeds this costs ``inf``.
    :param termination_cost: cost added once at a predicted termination (see ``terminated``).
    :param particles: rollouts per action sequence, their costs averaged (1: one rollout;
        PETS: 20 with trajectory sampling; docs/ilqr.md, "CEM", step 2).
    :param explore_weight: weight ``w`` of the disagreement bonus (0: off; see the module
        docstring); needs a model with ``disagreement(X, U)`` (``explore_on="state"``) or
        ``member_predictions(X, U)`` (``"cost"``): an ensemble.
    :param explore_on: ``"state"`` or ``"cost"``: what the members' disagreement is measured
        on (docs/agent.md, "Directed exploration").
    """

    samples: int = 200
    elites: int = 20
    iterations: int = 5
    init_std: float = 0.5
    smoothing: float = 0.1
    tol_std: float = 1e-3
    seed: int = 0
    max_state_norm: float = 1e8
    termination_cost: float = 0.0
    particles: int = 1
    explore_weight: float = 0.0
    explore_on: str = "state"

    def __post_init__(self) -> None:
        check_choice("options.explore_on", self.explore_on, ("state", "cost"))
        for name in ("samples", "elites", "iterations", "particles"):
            check_int(f"options.{name}", getattr(self, name), 1)
        if self.samples < 2:
            raise ValueError(f"options.samples must be >= 2, got {self.samples}")
        if self.elites > self.samples:
            raise ValueError(
                f"options.elites must be <= options.samples, got {self.elites} > {self.samples}")
        for name, lo, hi in (("init_std", 0.0, np.inf), ("smoothing", 0.0, 1.0),
                             ("tol_std", 0.0, np.inf), ("max_state_norm", 0.0, np.inf),
                             ("explore_weight", 0.0, np.inf)):
            v = getattr(self, name)
            if not isinstance(v, int | float) or not np.isfinite(v) or v < lo or v > hi:
                raise ValueError(f"options.{name} must be a finite number in [{lo}, {hi}], "
                                 f"got {v!r}")
        check_int("options.seed", self.seed, 0)
        if not np.isfinite(self.termination_cost):
            raise ValueError("options.termination_cost must be finite")


@dataclass(frozen=True)
class CEMResult:
    """Outcome of :func:`cem`.

    :param X: ``[T+1, n]`` model rollout of ``U`` (one row: with trajectory sampling, the
        first particle's).
    :param U: ``[T, m]`` the best sequence found (finite, inside the bounds).
    :param cost: its (task) cost (``inf`` if every rollout diverged).
    :param status: ``"converged"`` (std below ``tol_std``), ``"max_iter"`` or ``"failed"``
        (no finite rollout).
    :param iterations: iterations run.
    :param trace: per iteration ``{"iteration", "best_cost", "elite_mean_cost", "max_std",
        "time"}``; with ``explore_weight`` the costs are the ranking scores ``J - c D`` and
        ``"explore_scale"`` is ``c`` (``None`` until set).
    :param message: why it stopped.
    :param std: ``[T, m]`` the final sampling std.
    :param timings: seconds in ``rollout``, ``cost``, ``disagreement`` (with
        ``explore_weight``) and ``total``.
    :param disagreement: the model's disagreement ``D`` along ``X`` (``explore_weight > 0``;
        else ``None``).
    """

    X: np.ndarray
    U: np.ndarray
    cost: float
    status: str
    iterations: int
    trace: list[dict] = field(repr=False, default_factory=list)
    message: str = ""
    std: np.ndarray | None = field(repr=False, default=None)
    timings: dict = field(repr=False, default_factory=dict)
    disagreement: float | None = None


def _costs(
    cost: Any, X: np.ndarray, U: np.ndarray, t0: int, params: Any, done: np.ndarray | None,
    termination_cost: float,
) -> np.ndarray:
    """``[S]`` trajectory costs (docs/ilqr.md, "CEM", step 3; ``done``: the terminations)."""
    args = () if params is None else (params,)  # a cost without params takes no argument
    if done is None:
        return np.asarray(cost.total(X, U, t0, *args), dtype=float).reshape(X.shape[0])
    stage = np.asarray(cost.stage_values(X[:, :-1], U, t0, *args), dtype=float)
    final = np.asarray(cost.terminal_values(X[:, -1], t0 + U.shape[1], *args), dtype=float)
    return truncated_total(stage, final, done, termination_cost)


def cem(
    cost: Any,
    model: Any,
    x0: np.ndarray,
    U0: np.ndarray,
    *,
    u_min: np.ndarray | float,
    u_max: np.ndarray | float,
    params: Any = None,
    t0: int = 0,
    options: CEMOptions | dict | None = None,
    terminated: Callable[[np.ndarray], np.ndarray] | None = None,
) -> CEMResult:
    """Minimise ``J(U) = sum_t l(x_t, u_t, t0+t) + l_T(x_T)`` over ``U`` in the box with CEM,
    using only ``model.step`` (docs/ilqr.md, "CEM").

    :param cost: an object with ``total(X [..., T+1, n], U [..., T, m], t0[, params]) ->
        [...]`` (e.g. :class:`mbtsr.costs.CasadiCost`); with ``terminated`` also
        ``stage_values`` and ``terminal_values``.
    :param model: any model with batched ``step(x [..., n], u [..., m], t)``.
    :param x0: ``[n]`` initial state.
    :param U0: ``[T, m]`` initial mean of the sampling distribution (warm start), clipped.
    :param u_min: ``[m]`` or scalar lower bound (finite: CEM samples inside the box).
    :param u_max: ``[m]`` or scalar upper bound (finite).
    :param params: passed to the cost when given.
    :param t0: absolute time index of ``x0``.
    :param options: :class:`CEMOptions` or a dict of its fields.
    :param terminated: ``X [..., n] -> bool [...]``: predicted model states where the episode
        ends; stage costs after the first one are dropped.
    :return: :class:`CEMResult`.
    """
    opts = options_from(CEMOptions, options)
    x0, U0, t0, lo, hi = check_problem(model, x0, U0, t0, u_min, u_max, terminated)
    T, m = U0.shape
    explore = opts.explore_weight > 0
    need = "disagreement" if opts.explore_on == "state" else "member_predictions"
    if explore and not callable(getattr(model, need, None)):
        raise ValueError(
            f"options.explore_weight > 0 with explore_on={opts.explore_on!r} needs a model "
            f"with {need}(X, U) (an ensemble: mbtsr.ensemble.FrozenEnsemble), got "
            f"{type(model).__name__}")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("cem needs finite u_min and u_max (it samples inside the box)")
    if np.any(hi <= lo):
        raise ValueError(f"u_max must be > u_min, got u_min={lo}, u_max={hi}")
    half = 0.5 * (hi - lo)
    rng = np.random.default_rng(int(opts.seed))
    t_start = time.perf_counter()
    timings = {"rollout": 0.0, "cost": 0.0}

    mu = np.clip(U0, lo, hi)
    std = np.broadcast_to(opts.init_std * half, (T, m)).copy()
    best_U, best_J, best_cost, best_X = mu.copy(), np.inf, np.inf, None
    bonus = None  # c of directed exploration, set on the first iteration with a spread
    trace: list[dict] = []
    status, message = "max_iter", f"reached {opts.iterations} iterations"
    it = 0
    for it in range(1, opts.iterations + 1):
        tic = time.perf_counter()
        eps = rng.standard_normal((opts.samples, T, m))
        cand = np.clip(mu[None] + std[None] * eps, lo, hi)
        cand[0] = mu  # the current mean ...
        if np.isfinite(best_J):
            cand[1] = best_U  # ... and the best so far are always candidates
        tr = time.perf_counter()
        rows = cand if opts.particles == 1 else np.repeat(cand, opts.particles, axis=0)
        X, alive = _rollout(model, x0, rows, t0, opts.max_state_norm)
        tc = time.perf_counter()
        J, done = np.full(rows.shape[0], np.inf), None
        if alive.any():
            Xa = X[alive]  # one copy for the terminations and the costs
            done = terminations(terminated, Xa)
            J[alive] = _costs(cost, Xa, rows[alive], t0, params, done,
                              opts.termination_cost)
        J[~np.isfinite(J)] = np.inf
        if opts.particles > 1:
            J = J.reshape(opts.samples, opts.particles).mean(1)  # inf if any particle diverged
        timings["rollout"] += tc - tr
        timings["cost"] += time.perf_counter() - tc
        task_J = J
        if explore:
            td = time.perf_counter()
            D = _disagreements(model, cost, X, rows, alive, t0, params, opts, done)
            was = bonus
            J, bonus = _explore_scores(J, D, opts.explore_weight, bonus, opts.elites)
            if was is None and bonus is not None:
                best_J = np.inf  # scores change scale: the best so far is a candidate (cand[1])
            timings["disagreement"] = timings.get("disagreement", 0.0) + time.perf_counter() - td
        order = np.argsort(J, kind="stable")
        if J[order[0]] < best_J:
            best_J, best_U = float(J[order[0]]), cand[order[0]].copy()
            best_X = X[order[0] * opts.particles].copy()  # its (first particle's) rollout
            best_cost = float(task_J[order[0]])
        elite = order[: opts.elites]
        elite = elite[np.isfinite(J[elite])]
        if elite.size > 0:
            a = opts.smoothing
            mu = (1 - a) * cand[elite].mean(0) + a * mu
            std = (1 - a) * cand[elite].std(0) + a * std
        trace.append({
            "iteration": it,
            "best_cost": best_J,
            "elite_mean_cost": float(np.mean(J[elite])) if elite.size else np.inf,
            "max_std": float(np.max(std / half)),
            "time": time.perf_counter() - tic,
            **({"explore_scale": bonus} if explore else {}),
        })
        if np.max(std / half) < opts.tol_std:
            status, message = "converged", f"sampling std below tol_std={opts.tol_std}"
            break
    if not np.isfinite(best_J):
        status, message = "failed", "every sampled rollout diverged"
    if best_X is None:  # every rollout diverged: the plan's own (NaN from its divergence)
        best_X = _rollout(model, x0, best_U[None], t0, opts.max_state_norm)[0][0]
    X_best = best_X[None]
    D = None
    if explore:
        D = float(_disagreements(model, cost, X_best, best_U[None], np.ones(1, bool), t0,
                                 params, dataclasses.replace(opts, particles=1),
                                 terminations(terminated, X_best))[0])
    timings["total"] = time.perf_counter() - t_start
    X_out = X_best[0].copy()
    dead = ~np.isfinite(X_out).all(axis=-1)
    if dead.any():  # a diverged rollout holds its last finite state (X stays finite)
        first = int(np.argmax(dead))
        X_out[first:] = X_out[first - 1]
    return CEMResult(
        X=X_out, U=best_U, cost=best_cost, status=status, iterations=it, trace=trace,
        message=message, std=std, timings=timings, disagreement=D,
    )


def _disagreements(
    model: Any, cost: Any, X: np.ndarray, rows: np.ndarray, alive: np.ndarray, t0: int,
    params: Any, opts: CEMOptions, done: np.ndarray | None,
) -> np.ndarray:
    """``D [S]``: the members' disagreement summed along each sequence's rollout ``X [R, T+1,
    n]`` of ``rows [R, T, m]`` (``R = S x particles``, averaged over particles; 0 for dead
    rollouts), on the state or on the stage cost (``opts.explore_on``); with ``done`` (of the
    alive rollouts) the steps after the first predicted termination do
    not count (as their stage costs)."""
    D = np.zeros(rows.shape[0])
    if alive.any():
        Xa, Ua = X[alive, :-1], rows[alive]
        with np.errstate(all="ignore"):
            if opts.explore_on == "state":
                d = model.disagreement(Xa, Ua)
            else:  # std over members of the stage cost of their predicted next states
                P = model.member_predictions(Xa, Ua)  # [K, A, T, n]
                Uk = np.broadcast_to(Ua, (P.shape[0], *Ua.shape))
                args = () if params is None else (params,)
                d = np.asarray(cost.stage_values(P, Uk, t0 + 1, *args), dtype=float).std(0)
        if done is not None:
            d = np.where(after_termination(done), 0.0, d)
        D[alive] = np.sum(d, axis=-1)
    D[~np.isfinite(D)] = 0.0
    if opts.particles > 1:
        D = D.reshape(-1, opts.particles).mean(1)
    return D


def _explore_scores(
    J: np.ndarray, D: np.ndarray, weight: float, bonus: float | None, min_finite: int,
) -> tuple[np.ndarray, float | None]:
    """``(J - c D [S], c)``: the ranking scores of directed exploration (docs/agent.md),
    ``c`` fixed on the first call with at least ``min_finite`` (and 2) finite costs and a
    spread in both ``J`` and ``D`` over them (``None`` until then: the scores are ``J``)."""
    if bonus is None:
        ok = np.isfinite(J)
        if ok.sum() >= max(2, min_finite):
            sJ, sD = float(np.std(J[ok])), float(np.std(D[ok]))
            if sJ > 0 and sD > 0:
                bonus = weight * sJ / sD
    return (J if bonus is None else J - bonus * D), bonus

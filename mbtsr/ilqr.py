"""Iterative LQR with box control limits (control-limited DDP) on any dynamics model.

Solves ``min_U sum_t l(x_t, u_t, t0 + t) + l_T(x_T)`` s.t. ``x_{t+1} = f(x_t, u_t)``, ``u_min <=
u_t <= u_max`` for any :class:`mbtsr.dynamics.DynamicsModel` and :class:`mbtsr.costs.CasadiCost`,
with the control-limited DDP of Tassa, Mansard and Todorov (ICRA 2014) and the defaults of their
iLQG. The algorithm step by step: docs/ilqr.md, "iLQR".
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mbtsr import _lqr_kernels
from mbtsr.costs import CasadiCost, CostDerivatives, terminations, truncated_total
from mbtsr.dynamics import LinearDynamics, _rollout, check_planning_model, raw_step
from mbtsr.validation import as_array, check_callable, check_int, check_nonnegative, options_from

__all__ = ["ILQROptions", "ILQRResult", "ilqr", "check_control_bounds", "check_problem"]


@dataclass(frozen=True)
class ILQROptions:
    """Solver settings; defaults are those of the paper authors' iLQG (Tassa et al. 2014).

    :param max_iter: iteration cap (every iteration counts, accepted or not).
    :param tol_fun: converged when an accepted step lowers the cost by less than this (absolute).
    :param tol_fun_rel: also converged when an accepted step lowers the cost by less than
        ``tol_fun_rel * |J|`` (relative; 0 disables it, the authors' behaviour; see
        docs/ilqr.md, "Tolerances").
    :param tol_grad: converged when ``mean_t max_j |k_tj| / (|u_tj| + 1) < tol_grad`` while
        ``lambda < 1e-5``.
    :param lambda_init: initial Levenberg-Marquardt regularisation (0 gives a pure Newton step,
        e.g. the exact LQR solution in one iteration on a linear-quadratic problem).
    :param lambda_factor: growth factor of the adaptive schedule.
    :param lambda_max: give up (status ``"failed"``) when lambda exceeds this.
    :param lambda_min: lambda never drops below this after a decrease.
    :param alphas: line-search step sizes, largest first (rolled out in one batch or chunks).
    :param reg_type: 1 adds ``lambda I`` to ``Quu``; 2 adds ``lambda I`` to ``V'xx`` (state
        regularisation, ``Quu + lambda B^T B``, ``Qux + lambda B^T A``).
    :param reduce_ratio_min: accept a step when actual / expected improvement exceeds this.
    :param max_state_norm: a rollout whose ``max |x|`` exceeds this counts as diverged.
    :param termination_cost: with ``terminated``: cost paid once by a trajectory that
        terminates, instead of its terminal cost (see :func:`mbtsr.costs.truncated_total`).
    :param convexify_cost: project each stage's cost Hessian onto the positive semidefinite
        cone before the backward pass (:meth:`mbtsr.costs.CostDerivatives.convexified`; a
        no-op for convex costs; why: docs/ilqr.md, "Costs that are not convex").
    :param boxqp_*: projected-Newton box-QP settings (Tassa et al.'s ``boxQP`` defaults)."""

    max_iter: int = 500
    tol_fun: float = 1e-7
    tol_fun_rel: float = 0.0
    tol_grad: float = 1e-4
    lambda_init: float = 1.0
    lambda_factor: float = 1.6
    lambda_max: float = 1e10
    lambda_min: float = 1e-6
    alphas: tuple[float, ...] = tuple(float(a) for a in 10.0 ** np.linspace(0.0, -3.0, 11))
    reg_type: int = 1
    reduce_ratio_min: float = 0.0
    max_state_norm: float = 1e8
    termination_cost: float = 0.0
    convexify_cost: bool = True
    boxqp_max_iter: int = 100
    boxqp_min_grad: float = 1e-8
    boxqp_min_rel_improve: float = 1e-8
    boxqp_step_dec: float = 0.6
    boxqp_min_step: float = 1e-22
    boxqp_armijo: float = 0.1

    def __post_init__(self) -> None:
        check_int("max_iter", self.max_iter, 1)
        for name in ("tol_fun", "tol_fun_rel", "tol_grad", "lambda_init", "reduce_ratio_min"):
            check_nonnegative(name, getattr(self, name))
        for name in ("lambda_max", "lambda_min", "max_state_norm", "boxqp_min_step"):
            v = getattr(self, name)
            if not v > 0:
                raise ValueError(f"{name} must be > 0, got {v!r}")
        if not self.lambda_factor > 1:
            raise ValueError(f"lambda_factor must be > 1, got {self.lambda_factor!r}")
        a = np.asarray(self.alphas, dtype=float)
        if a.ndim != 1 or a.size < 1 or not np.all((a > 0) & (a <= 1)):
            raise ValueError(f"alphas must be a non-empty sequence in (0, 1], got {self.alphas!r}")
        if self.reg_type not in (1, 2):
            raise ValueError(f"reg_type must be 1 or 2, got {self.reg_type!r}")
        if not np.isfinite(self.termination_cost):
            raise ValueError(f"termination_cost must be finite, got {self.termination_cost!r}")
        if not 0 < self.boxqp_step_dec < 1 or not 0 < self.boxqp_armijo < 1:
            raise ValueError("boxqp_step_dec and boxqp_armijo must lie in (0, 1)")


@dataclass(frozen=True)
class ILQRResult:
    """Outcome of :func:`ilqr`.

    :param X: ``[T+1, n]`` state trajectory of the returned controls (under the model).
    :param U: ``[T, m]`` controls, always finite and within the bounds.
    :param K: ``[T, m, n]`` feedback gains of the last backward pass (rows of clamped controls
        are 0); the local policy is ``u_t = U_t + K_t (x_t - X_t)``, clipped to the bounds.
    :param k: ``[T, m]`` feed-forward step of the last backward pass (about 0 at convergence).
    :param cost: ``J(X, U)`` (``inf`` if no finite rollout was found).
    :param trace: one dict per iteration: ``iteration, cost, lambda, alpha, expected, actual,
        grad_norm, accepted, time`` (seconds spent in that iteration).
    :param status: ``"converged"``, ``"max_iter"`` or ``"failed"``.
    :param iterations: number of iterations run.
    :param message: why the solver stopped.
    :param lam: the final regularisation (useful to warm-start a next solve).
    :param timings: total seconds per phase: ``jacobians, cost_derivatives, backward, forward,
        line_search_cost, total``.
    :param proposal_cost: the cost of the initial plan a proposal step handed to iLQR (set by
        :func:`mbtsr.cem_ilqr.cem_ilqr`), else ``None``."""

    X: np.ndarray
    U: np.ndarray
    K: np.ndarray
    k: np.ndarray
    cost: float
    trace: list[dict] = field(repr=False)
    status: str
    iterations: int
    message: str
    lam: float = 1.0
    timings: dict = field(default_factory=dict, repr=False)
    proposal_cost: float | None = None


def check_control_bounds(u_min: object, u_max: object, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Validate box bounds: ``None`` (unbounded), a scalar or an ``[m]`` array each.

    :return: ``(lower [m], upper [m])`` with ``-inf`` / ``inf`` for missing bounds."""
    out = []
    for name, b, fill in (("u_min", u_min, -np.inf), ("u_max", u_max, np.inf)):
        if b is None:
            out.append(np.full(m, fill))
            continue
        arr = as_array(name, b, finite=False)
        if arr.ndim == 0:
            arr = np.full(m, float(arr))
        if arr.shape != (m,):
            raise ValueError(f"{name} must be a scalar or have shape [{m}], got {list(arr.shape)}")
        if np.any(np.isnan(arr)):
            raise ValueError(f"{name} contains NaN")
        out.append(arr.copy())
    lower, upper = out
    if np.any(lower > upper):
        i = int(np.argmax(lower > upper))
        raise ValueError(
            f"u_min must be <= u_max elementwise; at index {i}: u_min={lower[i]} > u_max={upper[i]}"
        )
    return lower, upper


def check_problem(
    model: object, x0: object, U0: object, t0: object, u_min: object, u_max: object,
    terminated: object, n: int | None = None, m: int | None = None,
) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray]:
    """Validate the arguments every optimizer shares (:func:`ilqr`'s): ``x0 [n]``, ``U0 [T >=
    1, m]`` (``n``, ``m``: ``None`` takes them from ``x0``, ``U0`` and checks the model's
    ``state_dim``/``action_dim``), ``t0 >= 0``, the bounds and ``terminated``.

    :return: ``(x0, U0, t0, lower [m], upper [m])``."""
    x0 = as_array("x0", x0, None if n is None else (n,), ndim=1)
    U0 = as_array("U0", U0, (None, m), ndim=2)
    if U0.shape[0] < 1 or U0.shape[1] < 1:
        raise ValueError(f"U0 must hold at least one time step (T >= 1) of m >= 1 inputs, got "
                         f"{list(U0.shape)}")
    for attr, arg, want in (("state_dim", "x0", x0.shape[0]), ("action_dim", "U0", U0.shape[1])):
        if getattr(model, attr, want) != want:
            raise ValueError(f"model.{attr}={getattr(model, attr)} does not match {arg}'s {want}")
    if terminated is not None:
        check_callable("terminated", terminated, "X -> bool")
    return x0, U0, check_int("t0", t0, 0), *check_control_bounds(u_min, u_max, U0.shape[1])


def ilqr(
    cost: CasadiCost,
    dynamics,
    x0: np.ndarray,
    U0: np.ndarray,
    *,
    u_min: np.ndarray | float | None = None,
    u_max: np.ndarray | float | None = None,
    params: np.ndarray | None = None,
    t0: int = 0,
    options: ILQROptions | None = None,
    terminated: Callable[[np.ndarray], np.ndarray] | None = None,
) -> ILQRResult:
    """Optimise a control sequence with control-limited iLQR (Tassa et al. 2014).

    The signature every optimizer of :class:`mbtsr.mpc.MPC` shares. All inputs are validated
    here, once; the iterations call the cost's and the model's unchecked kernels.

    :param cost: a :class:`mbtsr.costs.CasadiCost` with ``n, m`` matching the model.
    :param dynamics: a planning model (``model.freeze()`` of a learned ensemble, or a true /
        analytic / linear / LTV model): ``step(x[..., n], u[..., m], t)`` (batched) and
        ``jacobians(x[T, n], u[T, m], t0) -> (A [T, n, n], B [T, n, m])``; its optional
        ``_step`` (the same map without input checks) is used inside the loop.
    :param x0: ``[n]`` initial state.
    :param U0: ``[T, m]`` initial control sequence (clipped to the bounds).
    :param u_min: ``[m]`` (or scalar) lower control bound; ``None`` = unbounded.
    :param u_max: ``[m]`` (or scalar) upper control bound; ``None`` = unbounded.
    :param params: cost parameters, ``[p]`` or ``[N_ref, p]`` (a target, a reference; see
        :mod:`mbtsr.costs`); ``None``: the cost's defaults.
    :param t0: absolute time index of ``x0`` (passed to the cost and to time-varying models).
    :param options: :class:`ILQROptions` (or a dict of its fields).
    :param terminated: ``X [..., n] -> bool [...]``: model states where the episode ends; the
        line search then scores steps on the episode's own cost
        (:func:`mbtsr.costs.truncated_total`; docs/ilqr.md, "Predicted termination").
    :return: :class:`ILQRResult`. Its ``U`` is always finite and inside the bounds: a solve that
        meets NaN/inf (model, Jacobians, cost) stops with status ``"failed"`` and the best
        finite iterate."""
    opts = options_from(ILQROptions, options)
    if not isinstance(cost, CasadiCost):
        raise TypeError(f"cost must be a mbtsr.costs.CasadiCost, got {type(cost).__name__}")
    n, m = cost.n, cost.m
    check_planning_model(dynamics, n, m, name="dynamics")
    table = cost.check_params(params)
    x0, U0, t0, lower, upper = check_problem(dynamics, x0, U0, t0, u_min, u_max, terminated,
                                             n, m)
    has_limits = bool(np.any(np.isfinite(lower)) or np.any(np.isfinite(upper)))
    alphas = np.asarray(opts.alphas, dtype=float)
    boxqp_prm = tuple(float(getattr(opts, f"boxqp_{k}")) for k in (  # as BOXQP_DEFAULTS
        "max_iter", "min_grad", "min_rel_improve", "step_dec", "min_step", "armijo"))
    # step-size chunks of the forward pass: the model's chunk starts, else all at once
    n_a = len(alphas)
    starts = getattr(dynamics, "line_search_chunks", None) or (0,)
    if starts[0] != 0 or any(b <= a for a, b in zip(starts, starts[1:])):
        raise ValueError(f"line_search_chunks must start at 0 and increase, got {starts}")
    edges = [e for e in starts if e < n_a] + [n_a]
    chunks = [slice(a, b) for a, b in zip(edges[:-1], edges[1:])]
    T = U0.shape[0]
    timings = dict.fromkeys(
        ("jacobians", "cost_derivatives", "backward", "forward", "line_search_cost"), 0.0
    )
    t_start = time.perf_counter()

    # ---- initial rollout: U0, else scaled copies alpha * U0 (largest first)
    U = np.clip(U0, lower, upper)
    X, alive = _initial_rollout(dynamics, x0, U, t0, opts.max_state_norm)
    X = X[0]  # if every rollout diverges: the result's, NaN from the first diverged state on
    if not alive[0]:
        cands = np.clip(alphas[:, None, None] * U0[None], lower, upper)
        Xc, alive = _rollout(dynamics, x0, cands, t0, opts.max_state_norm)
        if alive.any():
            i = int(np.argmax(alive))
            X, U = Xc[i], cands[i]

    def total(X: np.ndarray, U: np.ndarray) -> np.ndarray:
        if terminated is None:
            return cost._total(X, U, t0, table)
        stage, final = cost._stage_and_terminal(X, U, t0, table)
        done = terminations(terminated, X)
        S = int(np.prod(stage.shape[:-1], dtype=np.int64))
        return truncated_total(stage.reshape(S, T), final.reshape(S), done.reshape(S, T),
                               opts.termination_cost).reshape(stage.shape[:-1])

    J = float(total(X, U)) if alive.any() else math.inf

    lam, dlam = float(opts.lambda_init), 1.0
    f = opts.lambda_factor
    K, k = np.zeros((T, m, n)), np.zeros((T, m))
    trace: list[dict] = []
    status, message = "", ""
    need_derivs = True
    it = 0
    problem = hessians = None
    if not alive.any():
        status, message = "failed", ("initial rollout diverged (non-finite or |x| > "
                                     "max_state_norm) for every scaled copy alpha * U0")
    elif not math.isfinite(J):
        status, message = "failed", "the cost of the initial trajectory is not finite"
    while not status and it < opts.max_iter:
        it += 1
        t_it = time.perf_counter()
        if need_derivs:
            tic = time.perf_counter()
            A, B = dynamics.jacobians(X[:-1], U, t0)
            A, B = np.asarray(A, dtype=float), np.asarray(B, dtype=float)
            if A.shape != (T, n, n) or B.shape != (T, n, m):
                raise ValueError(
                    f"dynamics.jacobians returned A {list(A.shape)}, B {list(B.shape)}; "
                    f"expected [{T}, {n}, {n}] and [{T}, {n}, {m}]"
                )
            timings["jacobians"] += time.perf_counter() - tic
            tic = time.perf_counter()
            derivs = cost._derivatives(X, U, t0, table)
            if opts.convexify_cost:
                derivs, hessians = _convexified(derivs, hessians)
            timings["cost_derivatives"] += time.perf_counter() - tic
            problem = (  # C-contiguous float64: one compiled signature of the kernels
                *(np.ascontiguousarray(a, dtype=float) for a in (A, B, *derivs)),
                lower - U,
                upper - U,
            )
            if not _lqr_kernels.all_finite(*problem[:7]):
                status = "failed"
                message = "non-finite Jacobians or cost derivatives at the current trajectory"
                break
            need_derivs = False

        # ---- backward pass, raising lambda until every Quu_reg is positive definite
        tic = time.perf_counter()
        while True:
            ok, *bp = _lqr_kernels.backward_pass(
                *problem, float(lam), opts.reg_type, has_limits, boxqp_prm
            )
            if ok:
                break
            bp = None
            dlam = max(dlam * f, f)
            lam = max(lam * dlam, opts.lambda_min)
            if lam > opts.lambda_max:
                break
        timings["backward"] += time.perf_counter() - tic
        if bp is None:
            status = "failed"
            message = "backward pass not positive definite up to lambda_max"
            break
        k, K, dV1, dV2 = bp
        grad_norm = _lqr_kernels.grad_norm(k, U)
        if grad_norm < opts.tol_grad and lam < 1e-5:
            dlam = min(dlam / f, 1.0 / f)
            lam = max(lam * dlam, opts.lambda_min) if lam > 0 else lam
            trace.append(_trace(it, J, lam, np.nan, 0.0, 0.0, grad_norm, False, t_it))
            status, message = "converged", "gradient norm below tol_grad"
            break

        # ---- forward pass: all step sizes in one batched rollout, or, for models whose step
        # cost grows with the batch (simulators), in growing chunks until one is acceptable;
        # either way the accepted step is the largest acceptable one
        expected = -alphas * (dV1 + alphas * dV2)
        Xn = np.empty((len(alphas), T + 1, n))
        Un = np.empty((len(alphas), T, m))
        alive = np.zeros(len(alphas), dtype=bool)
        Jn = np.full(len(alphas), np.inf)
        for chunk in chunks:
            tic = time.perf_counter()
            Xn[chunk], Un[chunk], alive[chunk] = _rollout_policy(
                dynamics, x0, X, U, k, K, alphas[chunk], lower, upper, t0, opts.max_state_norm
            )
            timings["forward"] += time.perf_counter() - tic
            tic = time.perf_counter()
            if alive[chunk].all():  # slices: no copies of the rollouts
                Jn[chunk] = total(Xn[chunk], Un[chunk])
            elif alive[chunk].any():
                live = np.zeros(len(alphas), dtype=bool)
                live[chunk] = alive[chunk]
                Jn[live] = total(Xn[live], Un[live])
            timings["line_search_cost"] += time.perf_counter() - tic
            actual = J - Jn
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = np.where(expected > 0, actual / expected, np.sign(actual))
            ok = alive & np.isfinite(Jn) & (ratio > opts.reduce_ratio_min)
            if ok.any():
                break
        if ok.any():
            i = int(np.argmax(ok))
            dcost = float(actual[i])
            X, U, J = Xn[i], Un[i], float(Jn[i])
            need_derivs = True
            dlam = min(dlam / f, 1.0 / f)
            lam = max(lam * dlam, opts.lambda_min)
            trace.append(_trace(it, J, lam, alphas[i], expected[i], dcost, grad_norm, True, t_it))
            if dcost < opts.tol_fun:
                status, message = "converged", "cost change below tol_fun"
                break
            if dcost < opts.tol_fun_rel * abs(J):
                status, message = "converged", "relative cost change below tol_fun_rel"
                break
        else:
            dlam = max(dlam * f, f)
            lam = max(lam * dlam, opts.lambda_min)
            a0 = float(actual[0]) if np.isfinite(actual[0]) else float("nan")
            trace.append(_trace(it, J, lam, np.nan, expected[0], a0, grad_norm, False, t_it))
            if alive[0] and expected[0] < opts.tol_fun and abs(actual[0]) < opts.tol_fun:
                status = "converged"
                message = "expected and actual cost change of the full step below tol_fun"
                break
            no_better = np.all(np.isfinite(Jn) & (Jn >= J - opts.tol_fun))
            if lam > opts.lambda_max and terminated is not None and no_better:
                # every step is finite and none improves the episode's (truncated) cost: the
                # plan is optimal under it, though the smooth cost's direction points elsewhere
                status = "converged"
                message = "no step improves the episode's cost (terminated) up to lambda_max"
                break
            if lam > opts.lambda_max:
                status = "failed"
                message = "line search found no improving step up to lambda_max"
                break
    if not status:
        status, message = "max_iter", f"reached max_iter={opts.max_iter}"
    timings["total"] = time.perf_counter() - t_start
    return ILQRResult(
        X=X,
        U=U,
        K=K,
        k=k,
        cost=J,
        trace=trace,
        status=status,
        iterations=it,
        message=message,
        lam=lam,
        timings=timings,
    )


# ----------------------------------------------------------------------------- internals
def _convexified(derivs: CostDerivatives, memo: tuple | None) -> tuple[CostDerivatives, tuple]:
    """``derivs.convexified()``, reusing the last projection when the Hessians are equal to
    the last ones (a constant-Hessian cost: no eigendecompositions after the first iteration).
    ``memo``: ``None`` or the ``(raw, projected)`` Hessian triples of the last call."""
    raw = (derivs.lxx, derivs.luu, derivs.lux)
    if memo is not None and all(np.array_equal(a, b) for a, b in zip(raw, memo[0])):
        return CostDerivatives(derivs.lx, derivs.lu, *memo[1]), memo
    out = derivs.convexified()
    return out, (raw, (out.lxx, out.luu, out.lux))


def _trace(it, J, lam, alpha, expected, actual, grad_norm, accepted, t_it) -> dict:
    return {
        "iteration": it,
        "cost": float(J),
        "lambda": float(lam),
        "alpha": float(alpha),
        "expected": float(expected),
        "actual": float(actual),
        "grad_norm": float(grad_norm),
        "accepted": bool(accepted),
        "time": time.perf_counter() - t_it,
    }


def _initial_rollout(dynamics, x0, U, t0, max_norm):
    """The open-loop rollout of ``U [T, m]`` -> ``(X [1, T+1, n], alive [1])``: through the
    model's compiled closed-loop rollout with zero gains when it has one (an affine model, the
    frozen ensemble: the same states, without ``T`` calls from Python), else (and for a
    diverged rollout, whose states must be NaN from the divergence on) :func:`_rollout`."""
    if type(dynamics) is LinearDynamics or getattr(dynamics, "_rollout_policy", None):
        T, m = U.shape
        n = x0.shape[0]
        Xn, _, alive = _rollout_policy(dynamics, x0, np.zeros((T + 1, n)), U, np.zeros((T, m)),
                                       np.zeros((T, m, n)), np.ones(1), np.full(m, -np.inf),
                                       np.full(m, np.inf), t0, max_norm)
        if alive[0]:
            return Xn, alive
    return _rollout(dynamics, x0, U[None], t0, max_norm)


def _rollout_policy(dynamics, x0, X, U, k, K, alphas, lower, upper, t0, max_norm):
    """Closed-loop rollouts for all step sizes at once.

    ``u_t = clip(U_t + alpha k_t + K_t (x_t - X_t))``; ``X: [T+1, n]``, ``U, k: [T, m]``,
    ``K: [T, m, n]``, ``alphas: [A]`` -> ``(Xn [A, T+1, n], Un [A, T, m], alive [A])``.
    A row that turns non-finite is marked dead and continues from the nominal state (so the
    model never sees NaN); rows exceeding ``max_norm`` are marked dead at the end. An affine
    model, or one with its own ``_rollout_policy`` (the frozen ensemble; ``None`` declines),
    rolls out in one compiled call with the same semantics."""
    kernel = getattr(dynamics, "_rollout_policy", None)  # a model's compiled rollouts
    if kernel is not None:
        out = kernel(x0, X, U, k, K, alphas, lower, upper, max_norm)
        if out is not None:
            return out
    if type(dynamics) is LinearDynamics:
        A, B, c = (
            np.ascontiguousarray(a, dtype=float)[None]
            for a in (dynamics.A, dynamics.B, dynamics.c)
        )
        return _lqr_kernels.rollout_policy_affine(
            A, B, c, x0, X, U, k, K, alphas, lower, upper, float(max_norm)
        )
    T, m = U.shape
    Xn, Un, alive = _lqr_kernels.rollout_buffers(x0, T, m, alphas.shape[0])
    step = raw_step(dynamics)
    policy = _lqr_kernels.policy_controls
    with np.errstate(all="ignore"):
        for t in range(T):
            policy(Xn, X, U, k, alphas, K, t, lower, upper, Un)
            xn = np.asarray(step(Xn[:, t], Un[:, t], t0 + t), dtype=float)
            if not math.isfinite(xn.sum()):
                bad = ~np.isfinite(xn).all(axis=-1)
                alive &= ~bad
                xn = np.where(bad[:, None], X[t + 1], xn)
            Xn[:, t + 1] = xn
        alive &= np.abs(Xn).max(axis=(1, 2)) <= max_norm
    return Xn, Un, alive

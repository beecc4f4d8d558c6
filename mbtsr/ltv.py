"""Linear time-varying (LTV) identification along trajectories: ``x_{t+1} = A_t x_t + B_t u_t
(+ c_t)``, smooth (:func:`fit_ltv`, :func:`select_lambda`) and piecewise (:func:`fit_ltv_tv`)
fits and prior fusion (:func:`fuse_prior`). The objectives, the banded information-form solver
and the covariances: docs/ltv.md. Notation: ``phi_t = [x_t; u_t; (1)]`` (``p`` regressors),
``k_t = [A_t B_t (c_t)]`` (``[n, p]``), ``G_t = sum_j phi^j_t phi^j_t^T``, ``H`` the block
tridiagonal normal-equation matrix shared by all output rows.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg.lapack import dpbtrf as _dpbtrf
from scipy.linalg.lapack import dpbtrs as _dpbtrs
from scipy.optimize import minimize_scalar

from mbtsr.dynamics import check_step_inputs
from mbtsr.trajectory import Trajectory, stack_trajectories
from mbtsr.validation import as_array, check_choice, check_int, check_nonnegative, check_positive

__all__ = ["LTVModel", "fit_ltv", "fit_ltv_tv", "select_lambda", "fuse_prior"]


# --------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class LTVModel:
    """A fitted LTV model ``x_{t+1} = A_t x_t + B_t u_t (+ c_t)``, ``t = 0..T-1``.

    Implements :class:`mbtsr.dynamics.DynamicsModel` (``step`` needs the time index ``t``).

    :param A: ``[T, n, n]`` state matrices.
    :param B: ``[T, n, m]`` input matrices.
    :param c: ``[T, n]`` affine terms, or ``None`` for a linear model.
    :param cov: ``[T, n, p, p]`` posterior covariance of output row ``i``'s parameters
        ``k_t^(i) = [A_t[i, :], B_t[i, :], (c_t[i])]``, ``p = n + m (+1)``, in absolute units.
    :param lam: regularization weight used in the fit.
    :param noise_var: pooled estimate of the one-step noise variance (mean over output rows).
    :param info: solver diagnostics (see the fitting functions).
    """

    A: np.ndarray
    B: np.ndarray
    c: np.ndarray | None
    cov: np.ndarray
    lam: float = 0.0
    noise_var: float = 0.0
    info: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        A = as_array("A", self.A, ndim=3)
        T, n = A.shape[0], A.shape[1]
        as_array("A", A, (T, n, n))
        B = as_array("B", self.B, (T, n, None))
        m = B.shape[2]
        c = None if self.c is None else as_array("c", self.c, (T, n))
        p = n + m + (c is not None)
        cov = as_array("cov", self.cov, (T, n, p, p), finite=False)
        if T < 1:
            raise ValueError("an LTV model needs T >= 1 time steps")
        for name, arr in (("A", A), ("B", B), ("c", c), ("cov", cov)):
            if arr is not None:
                arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "lam", float(self.lam))
        object.__setattr__(self, "noise_var", float(self.noise_var))

    # sizes ---------------------------------------------------------------------------------
    @property
    def T(self) -> int:  # noqa: N802 - the paper's symbol
        """Number of time steps (transitions) the model covers."""
        return self.A.shape[0]

    @property
    def state_dim(self) -> int:
        return self.A.shape[1]

    @property
    def action_dim(self) -> int:
        return self.B.shape[2]

    @property
    def affine(self) -> bool:
        return self.c is not None

    @property
    def params(self) -> np.ndarray:
        """``[T, n, p]`` stacked ``[A_t B_t (c_t)]``."""
        parts = [self.A, self.B] + ([self.c[:, :, None]] if self.c is not None else [])
        return np.concatenate(parts, axis=2)

    def _check_window(self, t0: int, length: int, what: str) -> None:
        if isinstance(t0, bool) or not isinstance(t0, int | np.integer):
            raise TypeError(f"t must be an int time index, got {t0!r}")
        if t0 < 0 or t0 + length > self.T:
            raise ValueError(f"{what}: time steps [{t0}, {t0 + length}) are outside the model's "
                             f"range [0, {self.T})")

    # the dynamics protocol ------------------------------------------------------------------
    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """``x_{t+1} = A_t x + B_t u (+ c_t)``.

        :param x: ``[..., n]`` states.
        :param u: ``[..., m]`` inputs (same leading dims).
        :param t: time index in ``[0, T)``; required for a time-varying model.
        :return: ``[..., n]`` next states.
        """
        if t is None:
            raise ValueError("LTVModel.step needs the time index t (the model is time-varying)")
        self._check_window(t, 1, "step")
        x, u = check_step_inputs(x, u, self.state_dim, self.action_dim)
        out = x @ self.A[t].T + u @ self.B[t].T
        return out + self.c[t] if self.c is not None else out

    def jacobians(self, x: np.ndarray, u: np.ndarray, t: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """``(A[t:t+T'], B[t:t+T'])`` for ``x: [T', n]``, ``u: [T', m]`` (values unused:
        the LTV Jacobians do not depend on the state)."""
        x = as_array("x", x, (None, self.state_dim))
        as_array("u", u, (x.shape[0], self.action_dim))
        self._check_window(t, x.shape[0], "jacobians")
        return self.A[t : t + x.shape[0]].copy(), self.B[t : t + x.shape[0]].copy()

    # using the model ------------------------------------------------------------------------
    def predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One-step predictions along a trajectory, time-aligned from ``t = 0``.

        :param x: ``[T', n]`` or ``[T'+1, n]`` states (a leading episode dim ``[N, ...]`` is
            allowed); a trailing ``x[T']`` is ignored.
        :param u: ``[T', m]`` or ``[N, T', m]`` inputs, ``T' <= T``.
        :return: ``[..., T', n]``; row ``t`` predicts ``x[t+1]``.
        """
        u = as_array("u", u)
        x = as_array("x", x)
        if u.ndim not in (2, 3) or u.shape[-1] != self.action_dim:
            raise ValueError(f"u must be [T', m] or [N, T', m] with m={self.action_dim}, "
                             f"got shape {list(u.shape)}")
        Tp = u.shape[-2]
        if (x.ndim != u.ndim or x.shape[:-2] != u.shape[:-2] or x.shape[-1] != self.state_dim
                or x.shape[-2] not in (Tp, Tp + 1)):
            raise ValueError(
                f"x must be [..., T' or T'+1, n] matching u {list(u.shape)} (the same episode "
                f"dim) with n={self.state_dim}, got shape {list(x.shape)}"
            )
        self._check_window(0, Tp, "predict")
        return self._predict(x[..., :Tp, :], u)

    def _predict(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """:meth:`predict` on validated ``x [..., T', n]`` (no trailing row), ``u [..., T', m]``."""
        Tp = u.shape[-2]
        out = np.einsum("tij,...tj->...ti", self.A[:Tp], x)
        out += np.einsum("tij,...tj->...ti", self.B[:Tp], u)
        return out + self.c[:Tp] if self.c is not None else out

    def sample_perturbed(
        self,
        x: np.ndarray,
        u: np.ndarray,
        *,
        sigma: float = 0.1,
        n_copies: int = 1,
        seed: int | np.random.Generator | None = None,
        std_x: np.ndarray | None = None,
        std_u: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Perturbed copies ``x~ = x + eps_x``, ``u~ = u + eps_u``, ``eps ~ N(0, (sigma std)^2)``
        of a trajectory labelled by the model, ``x~+_t = A_t x~_t + B_t u~_t (+ c_t)`` (sampled
        Jacobian propagation; docs/ltv.md, "Using the model").

        :param x: ``[T', n]`` or ``[T'+1, n]`` states (``x[T']`` unused), ``T' <= T``.
        :param u: ``[T', m]`` inputs.
        :param sigma: perturbation size relative to the per-dimension std (paper: 0.1).
        :param n_copies: number of perturbed copies.
        :param seed: int, ``numpy.random.Generator`` or ``None``.
        :param std_x: ``[n]`` per-dimension scale; default the std over time of ``x[:T']``
            (population std, ``ddof=0``). A dimension with zero std is not perturbed.
        :param std_u: ``[m]`` likewise for ``u``.
        :return: ``x_tilde [n_copies, T', n]``, ``u_tilde [n_copies, T', m]``,
            ``x_next_tilde [n_copies, T', n]``.
        """
        u = as_array("u", u, (None, self.action_dim))
        Tp = u.shape[0]
        x = as_array("x", x, (None, self.state_dim))
        if x.shape[0] not in (Tp, Tp + 1):
            raise ValueError(f"x must have T'={Tp} or T'+1 rows to match u, got {x.shape[0]}")
        self._check_window(0, Tp, "sample_perturbed")
        sigma = check_nonnegative("sigma", sigma)
        check_int("n_copies", n_copies, 1)
        x = x[:Tp]
        sx = x.std(axis=0) if std_x is None else as_array("std_x", std_x, (self.state_dim,))
        su = u.std(axis=0) if std_u is None else as_array("std_u", std_u, (self.action_dim,))
        if np.any(sx < 0) or np.any(su < 0):
            raise ValueError("std_x and std_u must be >= 0")
        return self._sample_perturbed(x, u, sigma, n_copies, np.random.default_rng(seed), sx, su)

    def _sample_perturbed(self, x, u, sigma: float, n_copies: int, rng: np.random.Generator,
                          sx: np.ndarray, su: np.ndarray) -> tuple:
        """:meth:`sample_perturbed` on validated input: ``x [T', n]`` or ``[T'+1, n]``,
        ``u [T', m]``, the scales ``sx [n]``, ``su [m]`` given."""
        Tp = u.shape[0]
        x_t = x[:Tp] + sigma * sx * rng.standard_normal((n_copies, Tp, self.state_dim))
        u_t = u + sigma * su * rng.standard_normal((n_copies, Tp, self.action_dim))
        return x_t, u_t, self._predict(x_t, u_t)


# --------------------------------------------------------------------------------------------
# Data handling
# --------------------------------------------------------------------------------------------


def _episodes(data: object) -> tuple[np.ndarray, np.ndarray]:
    """Normalize ``data`` to ``X [N, T+1, n]``, ``U [N, T, m]`` (float64, validated)."""
    if isinstance(data, Trajectory):
        X, U = data.x[None], data.u[None]
    elif isinstance(data, Sequence) and len(data) > 0 and all(
        isinstance(d, Trajectory) for d in data
    ):
        X, U = stack_trajectories(data, "data")
    elif isinstance(data, tuple) and len(data) == 2:
        X = as_array("x", data[0])
        U = as_array("u", data[1])
        if X.ndim == 2 and U.ndim == 2:
            X, U = X[None], U[None]
        if X.ndim != 3 or U.ndim != 3:
            raise ValueError(
                f"data: x must be [T+1, n] or [N, T+1, n] and u [T, m] or [N, T, m] of the same "
                f"rank, got x {list(X.shape)} and u {list(U.shape)}"
            )
    else:
        raise TypeError(
            "data must be a Trajectory, a non-empty list of Trajectory, or a tuple (x, u) of "
            f"arrays; got {type(data).__name__}"
        )
    if X.shape[0] != U.shape[0]:
        raise ValueError(f"data: x has {X.shape[0]} episodes but u has {U.shape[0]}")
    if X.shape[1] != U.shape[1] + 1:
        raise ValueError(f"data: need len(x) == len(u) + 1 per episode, got x {list(X.shape)} and "
                         f"u {list(U.shape)}")
    if U.shape[1] < 2:
        raise ValueError(f"data: an LTV fit needs T >= 2 transitions, got T={U.shape[1]}")
    if X.shape[0] < 1 or X.shape[2] < 1 or U.shape[2] < 1:
        raise ValueError(f"data: empty dimension in x {list(X.shape)} or u {list(U.shape)}")
    return X, U


@dataclass(frozen=True)
class _Problem:
    """Sufficient statistics of the regression, shared by every lambda."""

    G: np.ndarray  # [T, p, p]  sum_j phi phi^T
    R: np.ndarray  # [T, p, n]  sum_j phi y^T
    Phi: np.ndarray  # [N, T, p]
    Y: np.ndarray  # [N, T, n]
    n: int
    m: int
    affine: bool

    def __post_init__(self) -> None:  # sizes; M: measurements per output row
        N, T, p = self.Phi.shape  # noqa: N806
        for name, value in (("N", N), ("T", T), ("p", p), ("M", N * T)):
            object.__setattr__(self, name, value)


def _problem(data: object, affine: bool) -> _Problem:
    X, U = _episodes(data)
    parts = [X[:, :-1], U] + ([np.ones(U.shape[:2] + (1,))] if affine else [])
    Phi = np.concatenate(parts, axis=2)
    Y = X[:, 1:]
    G = np.einsum("jtp,jtq->tpq", Phi, Phi)
    R = np.einsum("jtp,jti->tpi", Phi, Y)
    return _Problem(G, R, Phi, Y, X.shape[2], U.shape[2], bool(affine))


def _check_lam(lam: float) -> float:
    if isinstance(lam, bool):
        raise TypeError("lam must be a number")
    return check_nonnegative("lam", lam)


# --------------------------------------------------------------------------------------------
# Banded block-tridiagonal algebra (lower band storage: ab[k, j] = H[j + k, j])
# --------------------------------------------------------------------------------------------


def _band(G: np.ndarray, lam2: float, ridge0: float = 0.0) -> np.ndarray:
    """Lower band storage ``[p+1, T p]`` of ``H = blkdiag(G_t) + lam2 * D^T D (+ ridge0 at t=0)``.

    ``D`` is the block first-difference operator; ``D^T D`` has ``1, 2, ..., 2, 1`` on its
    block diagonal and ``-1`` on the block off-diagonals.
    """
    T, p, _ = G.shape
    ab = np.zeros((p + 1, T * p))
    _put_diagonal_blocks(ab, G)
    ab[0] += np.repeat(_penalty_diagonal(T, lam2, ridge0), p)
    ab[p, : (T - 1) * p] = -lam2
    return ab


def _penalty_diagonal(T: int, lam2: float, ridge0: float) -> np.ndarray:
    """``[T]`` the scalar of ``I`` in each diagonal block of ``lam2 D^T D + ridge0 e_0 e_0^T``."""
    d = np.full(T, 2.0 * lam2)
    d[0] = d[-1] = lam2
    d[0] += ridge0
    return d


def _put_diagonal_blocks(ab: np.ndarray, blocks: np.ndarray) -> None:
    """Write the lower triangles of the diagonal blocks ``blocks [T, p, p]`` into the lower band
    storage ``ab [rows, T p]`` (row ``k`` holds the ``k``-th subdiagonal:
    ``ab[k, t p + j] = blocks[t, j + k, j]``)."""
    T, p, _ = blocks.shape
    k, j = _band_index(p)
    ab.reshape(ab.shape[0], T, p)[k, :, j] = blocks[:, j + k, j].T


@functools.lru_cache(maxsize=32)
def _band_index(p: int) -> tuple[np.ndarray, np.ndarray]:
    """``(k, j)`` of every entry ``(j + k, j)`` of a ``p x p`` block's lower triangle."""
    k = np.concatenate([np.full(p - i, i) for i in range(p)])
    j = np.concatenate([np.arange(p - i) for i in range(p)])
    k.setflags(write=False)  # cached: shared by every call
    j.setflags(write=False)
    return k, j


def _reverse_band(ab: np.ndarray) -> np.ndarray:
    """Band storage of ``J H J`` with ``J`` the full index reversal."""
    out = np.empty_like(ab)
    L = ab.shape[1]
    for k in range(ab.shape[0]):
        out[k, : L - k] = ab[k, : L - k][::-1]
        out[k, L - k :] = 0.0
    return out


def _diag_blocks_of_LLt(cb: np.ndarray, T: int, p: int) -> np.ndarray:
    """``[T, p, p]`` diagonal blocks ``L_tt L_tt^T`` of a banded Cholesky factor (the Schur
    complements of the elimination)."""
    k, j = _band_index(p)
    L = np.zeros((T, p, p))
    L[:, j + k, j] = cb.reshape(p + 1, T, p)[k, :, j].T
    return L @ L.transpose(0, 2, 1)


class _NotPositiveDefinite(Exception):
    def __init__(self, index: int) -> None:
        self.index = index


def _cholesky(ab: np.ndarray) -> np.ndarray:
    """Banded Cholesky factor (LAPACK ``dpbtrf``, called directly: scipy's wrapper adds a few
    microseconds of checks per call, which counts at small ``T``)."""
    cb, info = _dpbtrf(ab, lower=1)
    if info > 0:
        raise _NotPositiveDefinite(info - 1)
    if info < 0:  # pragma: no cover - a malformed call, not a property of the data
        raise ValueError(f"dpbtrf: illegal value in argument {-info}")
    return cb


def _cho_solve_band(cb: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``H X = rhs`` from :func:`_cholesky`'s factor (LAPACK ``dpbtrs``)."""
    x, info = _dpbtrs(cb, rhs, lower=1)
    if info != 0:  # pragma: no cover - a malformed call
        raise ValueError(f"dpbtrs: illegal value in argument {-info}")
    return x


def _singular_message(prob: _Problem, lam: float, index: int) -> str:
    t = max(index, 0) // prob.p
    if lam == 0.0:
        return (
            f"lam=0: the per-time least-squares problem at t={t} is singular (the {prob.N} "
            f"regressor vector(s) phi_t = [x_t; u_t{'; 1' if prob.affine else ''}] do not span "
            f"R^{prob.p}); use lam > 0"
        )
    Gsum = prob.G.sum(axis=0)
    if np.linalg.eigvalsh(Gsum)[0] <= 1e-12 * np.trace(Gsum) / prob.p:
        return (
            "the regressors are not persistently exciting: sum_t phi_t phi_t^T is singular (for "
            "example a constant or zero input, or an affine term with constant regressors); "
            "excite the system, drop affine=True, or pass P0 to add a prior on k_0"
        )
    s2 = float(np.trace(Gsum)) / (prob.T * prob.p)
    if lam * lam > s2:  # the penalty dominates: the data terms drown in its rounding
        return (
            f"the normal equations are numerically singular at lam={lam:.3g} (near t={t}): lam "
            "is so large that the data terms are lost in the rounding of the smoothness penalty "
            f"in float64; use a smaller lam, or lam >= {np.sqrt(_LIMIT * s2):.3g}, where the fit "
            "takes its exact lam -> inf limit (time-invariant least squares)"
        )
    return (
        f"the normal equations are numerically singular at lam={lam:.3g} (near t={t}):"
        f" with {prob.N} measurement(s) per time step and {prob.p} parameters the fit relies "
        "on the smoothness penalty, and lam is too small for float64; increase lam"
    )


# beyond lam^2 = _LIMIT * s^2 (s^2 the mean per-step regressor power) the data terms vanish
# below the rounding of H's diagonal; the fit then returns the lam -> inf limit.
_LIMIT = 1e14


@dataclass(frozen=True)
class _L2Solution:
    theta: np.ndarray  # [T, p, n]
    ab: np.ndarray | None  # band storage of H (None in the lam -> inf limit)
    cb: np.ndarray | None  # its banded Cholesky factor
    rss: np.ndarray  # [n]
    penalty: np.ndarray  # [n] lam^2 ||D theta||^2 (+ ridge0 ||theta_0||^2)
    logdet: float  # log det H (its lam -> inf asymptote in that limit)
    Gsum_inv: np.ndarray | None  # (sum_t G_t)^{-1} if it exists


def _solve_l2(prob: _Problem, lam: float, ridge0: float = 0.0) -> _L2Solution:
    """Banded Cholesky solve of ``H theta = R`` for all ``n`` output rows at once.

    The solve is deflated around the time-invariant least-squares solution ``theta_bar``
    (``theta = theta_bar + delta``, ``H delta = R - H (1 kron theta_bar)``): the rounding error
    of the banded solve, about ``eps cond(H)`` relative to the unknown, then scales with the
    small ``delta`` instead of ``theta`` when ``lam`` is large.
    """
    T, p, n = prob.T, prob.p, prob.n
    lam2 = lam * lam
    Gsum = prob.G.sum(axis=0)
    try:
        Gsum_chol = np.linalg.cholesky(Gsum)
        Gsum_inv = np.linalg.inv(Gsum)
        theta_bar = Gsum_inv @ prob.R.sum(axis=0)  # [p, n]
    except np.linalg.LinAlgError:
        Gsum_inv, theta_bar = None, np.zeros((p, n))
    s2 = float(np.trace(Gsum)) / (T * p)
    if Gsum_inv is not None and lam2 >= _LIMIT * s2 and ridge0 == 0.0:
        theta, ab, cb = np.broadcast_to(theta_bar, (T, p, n)).copy(), None, None
        # log det H in the same limit: H -> blkdiag(G_t) + lam^2 (L kron I_p), L the path
        # Laplacian whose nonzero eigenvalues multiply to T, so that det H -> lam^(2 (T-1) p)
        # det(sum_t G_t) (the constant direction keeps (1/T) sum_t G_t, times T^p)
        logdet = (2.0 * float(np.sum(np.log(np.diag(Gsum_chol))))
                  + 2.0 * (T - 1) * p * float(np.log(lam)))
    else:
        ab = _band(prob.G, lam2, ridge0)
        try:
            cb = _cholesky(ab)
        except _NotPositiveDefinite as err:
            raise ValueError(_singular_message(prob, lam, err.index)) from None
        rhs = prob.R - prob.G @ theta_bar
        rhs[0] -= ridge0 * theta_bar
        delta = _cho_solve_band(cb, rhs.reshape(T * p, n))
        theta = theta_bar + delta.reshape(T, p, n)
        logdet = 2.0 * float(np.sum(np.log(cb[0])))
    resid = prob.Y - np.einsum("jtp,tpi->jti", prob.Phi, theta)
    rss = np.einsum("jti,jti->i", resid, resid)
    dth = np.diff(theta, axis=0)
    penalty = np.zeros(n) if cb is None else lam2 * np.einsum("tpi,tpi->i", dth, dth)
    penalty = penalty + ridge0 * np.einsum("pi,pi->i", theta[0], theta[0])
    return _L2Solution(theta, ab, cb, rss, penalty, logdet, Gsum_inv)


def _marginal_blocks(prob: _Problem, sol: _L2Solution, lam: float, ridge0: float) -> np.ndarray:
    """``[T, p, p]`` diagonal blocks of ``H^{-1}`` (two-filter formula in information form:
    ``(F_t + B_t - H_tt)^{-1}`` with ``F_t``, ``B_t`` the Schur complements of block ``t`` after
    eliminating all earlier / later blocks, read off a forward and a reversed banded Cholesky).
    """
    T, p = prob.T, prob.p
    lam2 = lam * lam
    if sol.cb is None:  # lam -> inf: every block of H^{-1} tends to (sum_t G_t)^{-1}
        return np.broadcast_to(sol.Gsum_inv, (T, p, p)).copy()
    forward = _diag_blocks_of_LLt(sol.cb, T, p)
    try:
        cb_rev = _cholesky(_reverse_band(sol.ab))
    except _NotPositiveDefinite as err:  # pragma: no cover - H already factored forward
        raise ValueError(_singular_message(prob, lam, err.index)) from None
    backward = _diag_blocks_of_LLt(cb_rev, T, p)[::-1, ::-1, ::-1]
    blocks = forward + backward - prob.G  # minus H_tt = G_t + d_t I
    i = np.arange(p)
    blocks[:, i, i] -= _penalty_diagonal(T, lam2, ridge0)[:, None]
    try:
        Sigma = np.linalg.inv(blocks)
    except np.linalg.LinAlgError:  # the factorization passed, a block of H^{-1} did not
        bad = next((t for t in range(T) if np.linalg.matrix_rank(blocks[t]) < p), 0)
        raise ValueError(_singular_message(prob, lam, bad)) from None
    return 0.5 * (Sigma + Sigma.transpose(0, 2, 1))


def _neg_log_marglik(prob: _Problem, sol: _L2Solution, lam: float) -> float:
    """Negative diffuse log marginal likelihood of the random-walk model, each output row's
    noise variance profiled out (``sigma_i^2 = S_i / (M - p)``)::

        -log L = sum_i (M-p)/2 [log(2 pi S_i/(M-p)) + 1] + n/2 log det H - n (T-1) p log lam
    """
    dof = prob.M - prob.p
    S = np.maximum(sol.rss + sol.penalty, np.finfo(float).tiny)
    val = 0.5 * dof * np.sum(np.log(2.0 * np.pi * S / dof) + 1.0)
    val += 0.5 * prob.n * sol.logdet - 0.5 * prob.n * (prob.T - 1) * prob.p * 2.0 * np.log(lam)
    return float(val)


def _split_theta(theta: np.ndarray, n: int, m: int, affine: bool):
    """``theta [T, p, n]`` -> ``A [T, n, n], B [T, n, m], c [T, n] | None``."""
    k = theta.transpose(0, 2, 1)
    A = np.ascontiguousarray(k[:, :, :n])
    B = np.ascontiguousarray(k[:, :, n : n + m])
    c = np.ascontiguousarray(k[:, :, n + m]) if affine else None
    return A, B, c


# --------------------------------------------------------------------------------------------
# Smooth (L2) fit
# --------------------------------------------------------------------------------------------


def fit_ltv(data: object, lam: float, *, affine: bool = False, P0: float | None = None) -> LTVModel:
    """Smooth LTV fit: the exact minimizer of (paper eq. (3), ``ltvmodels``) ::

        sum_{t,j} ||x^j_{t+1} - A_t x^j_t - B_t u^j_t (- c_t)||^2 + lam^2 sum_t ||k_{t+1} - k_t||^2

    by a banded Cholesky solve (``O(T (n+m)^3)``; docs/ltv.md, "The smooth (L2) fit").

    :param data: a :class:`~mbtsr.trajectory.Trajectory`, a list of aligned trajectories (same
        ``T``; every episode contributes a measurement at every ``t``), or a tuple ``(x, u)``
        with ``x: [T+1, n]`` or ``[N, T+1, n]`` and ``u: [T, m]`` or ``[N, T, m]``.
    :param lam: regularization weight ``>= 0``. In the original's Kalman form
        ``lam^2 = R2 / R1`` (measurement / drift variance). ``lam = 0`` fits every ``t``
        separately and needs ``N >= p`` episodes.
    :param affine: also fit an affine term ``c_t``.
    :param P0: optional prior ``k_0 ~ N(0, P0 * sigma^2 I)`` (adds ``||k_0||^2 / P0``); ``None``
        (default) is the diffuse prior, i.e. the exact minimizer above.
    :return: :class:`LTVModel`; ``info`` holds ``edf`` (effective number of parameters per
        row, ``tr(H^{-1} sum_t G_t)``), ``rss [n]``, ``noise_var_rows [n]``
        (``rss_i / (N T - edf)``), ``neg_log_marglik`` (see :func:`select_lambda`; ``None``
        if ``P0`` is given or ``N T <= p``), ``solver``.
    """
    lam = _check_lam(lam)
    ridge0 = 0.0
    if P0 is not None:
        ridge0 = 1.0 / check_positive("P0", P0)
    return _l2_model(_problem(data, affine), lam, ridge0)


def _l2_model(prob: _Problem, lam: float, ridge0: float) -> LTVModel:
    if lam == 0.0 and ridge0 == 0.0 and prob.N < prob.p:
        raise ValueError(
            f"lam=0 leaves the problem under-determined: {prob.N} measurement(s) per time step "
            f"but {prob.p} parameters per output row; use lam > 0 or at least {prob.p} aligned "
            "episodes"
        )
    sol = _solve_l2(prob, lam, ridge0)
    Sigma = _marginal_blocks(prob, sol, lam, ridge0)
    edf = float(np.einsum("tpq,tqp->", Sigma, prob.G))
    dof = max(prob.M - edf, 1e-12)
    noise_rows = sol.rss / dof
    A, B, c = _split_theta(sol.theta, prob.n, prob.m, prob.affine)
    cov = noise_rows[None, :, None, None] * Sigma[:, None]
    nlml = None
    if ridge0 == 0.0 and lam > 0 and prob.M > prob.p and sol.logdet is not None:
        nlml = _neg_log_marglik(prob, sol, lam)
    info = {
        "solver": "banded_cholesky",
        "edf": edf,
        "rss": sol.rss,
        "noise_var_rows": noise_rows,
        "neg_log_marglik": nlml,
        "n_episodes": prob.N,
    }
    return LTVModel(A, B, c, cov, lam=lam, noise_var=float(np.mean(noise_rows)), info=info)


# --------------------------------------------------------------------------------------------
# Automatic lambda
# --------------------------------------------------------------------------------------------


def _score(prob: _Problem, lam: float, method: str) -> float:
    sol = _solve_l2(prob, lam)
    if method == "marginal_likelihood":
        return _neg_log_marglik(prob, sol, lam)
    Sigma = _marginal_blocks(prob, sol, lam, 0.0)
    edf = float(np.einsum("tpq,tqp->", Sigma, prob.G))
    frac = max(1.0 - edf / prob.M, 1e-300)
    rss = np.maximum(sol.rss / prob.M, np.finfo(float).tiny)
    return float(np.sum(np.log(rss)) - 2.0 * prob.n * np.log(frac))


def select_lambda(
    data: object,
    lambdas: Sequence[float] | np.ndarray | None = None,
    *,
    method: str = "marginal_likelihood",
    affine: bool = False,
) -> tuple[float, dict]:
    """Choose ``lam`` for :func:`fit_ltv` from the data (docs/ltv.md, "Automatic lambda").

    :param method: ``"marginal_likelihood"`` (the random-walk model's diffuse log marginal
        likelihood, noise variances profiled out) or ``"gcv"`` (generalized cross-validation
        per output row).
    :param lambdas: grid of candidates ``> 0``; default 36 log-spaced values from
        ``1e-3 s`` to ``1e4 s`` with ``s = sqrt(mean_t tr(G_t) / p)`` the regressor scale.
    :return: ``(lam, curve)`` with ``curve = {"lambdas", "score" (lower is better; NaN where
        skipped), "method", "grid_best", "at_boundary", "skipped"}``. Grid points whose fit is
        numerically singular are skipped (listed in ``skipped``, one warning; all singular is an
        error); a minimizer at the edge of the usable grid warns.
    """
    check_choice("method", method, ("marginal_likelihood", "gcv"))
    prob = _problem(data, affine)
    if prob.M <= prob.p:
        raise ValueError(
            f"select_lambda needs more measurements per output row (N T = {prob.M}) than "
            f"parameters per time step (p = {prob.p})"
        )
    if lambdas is None:
        scale = np.sqrt(np.mean(np.trace(prob.G, axis1=1, axis2=2)) / prob.p)
        lambdas = scale * np.logspace(-3, 4, 36)
    lambdas = as_array("lambdas", lambdas, ndim=1)
    if lambdas.size < 1 or np.any(lambdas <= 0):
        raise ValueError("lambdas must be a non-empty 1-D array of values > 0")
    lambdas = np.sort(lambdas)
    scores, singular = np.full(lambdas.size, np.nan), []
    for i, lam in enumerate(lambdas):
        try:
            scores[i] = _score(prob, float(lam), method)
        except ValueError as err:  # numerically singular at this lam: skipped, reported
            singular.append((float(lam), str(err)))
    if len(singular) == lambdas.size:
        raise ValueError(f"select_lambda: the fit is numerically singular at every lambda in the "
                         f"grid; at lam={singular[0][0]:.3g}: {singular[0][1]}")
    if singular:
        warnings.warn(
            f"select_lambda: skipped {len(singular)} of {lambdas.size} grid values whose fit is "
            f"numerically singular (lam = {', '.join(f'{v:.3g}' for v, _ in singular[:5])}"
            f"{', ...' if len(singular) > 5 else ''}; curve['skipped'] lists them)",
            RuntimeWarning,
            stacklevel=2,
        )
    if not np.any(np.isfinite(scores)):
        raise ValueError("select_lambda: the criterion is not finite for any lambda in the grid")
    usable = np.flatnonzero(np.isfinite(scores))
    best = int(usable[np.argmin(scores[usable])])
    lam_best = float(lambdas[best])
    at_boundary = usable.size > 1 and best in (usable[0], usable[-1])
    if at_boundary:
        warnings.warn(
            f"select_lambda ({method}): the best lambda {lam_best:.3g} is at the edge of the grid "
            f"[{lambdas[0]:.3g}, {lambdas[-1]:.3g}]; the criterion may prefer a more extreme value",
            RuntimeWarning,
            stacklevel=2,
        )
    elif usable.size > 2:  # refine: a bounded 1-D search in log lam between the neighbours
        k = int(np.searchsorted(usable, best))
        lo, hi = np.log(lambdas[usable[k - 1]]), np.log(lambdas[usable[k + 1]])

        def score(log_lam: float) -> float:
            try:
                return _score(prob, float(np.exp(log_lam)), method)
            except ValueError:  # singular between the grid points: not a candidate
                return np.inf

        res = minimize_scalar(score, bounds=(lo, hi), method="bounded",
                              options={"xatol": 1e-3})
        if res.success and res.fun <= scores[best]:
            lam_best = float(np.exp(res.x))
    curve = {
        "lambdas": lambdas.tolist(),
        "score": scores.tolist(),
        "method": method,
        "grid_best": float(lambdas[best]),
        "at_boundary": bool(at_boundary),
        "skipped": [v for v, _ in singular],
    }
    return lam_best, curve


# --------------------------------------------------------------------------------------------
# Piecewise (TV / group-lasso) fit
# --------------------------------------------------------------------------------------------


def _group_shrink(v: np.ndarray, thresh: float) -> np.ndarray:
    """Block soft-threshold, the prox of ``thresh * sum_t ||v_t||_2``: ``v [T-1, p, n]``."""
    norms = np.sqrt(np.einsum("tpi,tpi->t", v, v))
    scale = np.maximum(1.0 - thresh / np.maximum(norms, 1e-300), 0.0)
    return v * scale[:, None, None]


def _diff_T(v: np.ndarray) -> np.ndarray:
    """``D^T v`` for ``v [T-1, ...]`` -> ``[T, ...]`` (``(D theta)_t = theta_{t+1} - theta_t``)."""
    out = np.zeros((v.shape[0] + 1,) + v.shape[1:])
    out[1:] += v
    out[:-1] -= v
    return out


def _segments(starts: np.ndarray, T: int) -> np.ndarray:
    """``[T]`` segment index of every time step, segments starting at ``starts`` (``[0, ...]``)."""
    seg = np.zeros(T, int)
    seg[starts[1:]] = 1
    return np.cumsum(seg)


def _tv_objective(prob: _Problem, theta: np.ndarray, lam: float) -> float:
    resid = prob.Y - np.einsum("jtp,tpi->jti", prob.Phi, theta)
    dth = np.diff(theta, axis=0)
    return float(np.sum(resid**2) + lam * np.sum(np.sqrt(np.einsum("tpi,tpi->t", dth, dth))))


def _block_tridiag_band(diag: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """Lower band storage ``[2q, S q]`` of the symmetric block-tridiagonal matrix with diagonal
    blocks ``diag [S, q, q]`` and sub-diagonal blocks ``lower [S-1, q, q]``
    (``H[(s+1) q + a, s q + b] = lower[s, a, b]``)."""
    S, q, _ = diag.shape
    ab = np.zeros((2 * q, S * q))
    _put_diagonal_blocks(ab, diag)
    idx = np.arange(q)
    for k in range(1, 2 * q):
        b = idx[max(0, q - k) : min(q, 2 * q - k)]
        ab[k].reshape(S, q)[:-1, b] = lower[:, b + k - q, b]
    return ab


def _newton_segments(
    prob: _Problem, lam: float, K: np.ndarray, Gs: np.ndarray, Rs: np.ndarray, fscale: float
) -> tuple[str, np.ndarray]:
    """Damped Newton on ``sum_s [tr(K_s^T G_s K_s) - 2 tr(K_s^T R_s)] + lam sum ||K_j - K_{j-1}||``.

    :return: ``("ok", K)``, ``("vanished", K)`` if a jump collapsed to zero, or ``("fail", K)``.
    """
    S, p, n = K.shape
    q = p * n
    scale = np.sqrt(np.mean(K**2)) + 1e-300

    def value(K_: np.ndarray) -> float:
        quad = np.einsum("spi,spq,sqi->", K_, Gs, K_) - 2.0 * np.einsum("spi,spi->", K_, Rs)
        d = np.diff(K_, axis=0)
        return float(quad + lam * np.sum(np.sqrt(np.einsum("spi,spi->s", d, d))))

    f = value(K)
    for _ in range(50):
        d = np.diff(K, axis=0)  # [S-1, p, n]
        norms = np.sqrt(np.einsum("spi,spi->s", d, d))
        if np.any(norms <= 1e-9 * scale):
            return "vanished", K
        unit = d / norms[:, None, None]
        grad = 2.0 * (Gs @ K - Rs)
        grad[1:] += lam * unit
        grad[:-1] -= lam * unit
        # Hessian, ordering vec(K_s) = K_s.T.ravel(): block tridiagonal with q x q blocks
        diag = np.zeros((S, q, q))
        for i in range(n):
            diag[:, i * p : (i + 1) * p, i * p : (i + 1) * p] = 2.0 * Gs
        uv = unit.transpose(0, 2, 1).reshape(S - 1, q)
        M = (lam / norms)[:, None, None] * (np.eye(q) - uv[:, :, None] * uv[:, None, :])
        diag[:-1] += M
        diag[1:] += M
        ab = _block_tridiag_band(diag, -M)
        ab[0] += 1e-12 * np.mean(ab[0])
        g = grad.transpose(0, 2, 1).reshape(-1)
        try:
            cb = _cholesky(ab)
        except _NotPositiveDefinite:
            return "fail", K
        step = -_cho_solve_band(cb, g)
        decrement = -float(g @ step)
        if decrement <= 1e-22 * fscale:
            return "ok", K
        dK = step.reshape(S, n, p).transpose(0, 2, 1)
        alpha = 1.0
        for _ls in range(40):
            f_new = value(K + alpha * dK)
            if f_new <= f - 1e-4 * alpha * decrement:
                break
            alpha *= 0.5
        else:
            if decrement <= 1e-14 * fscale:
                return "ok", K
            return ("vanished" if norms.min() <= 1e-4 * scale else "fail"), K
        K, f = K + alpha * dK, f_new
    d = np.diff(K, axis=0)
    small = np.sqrt(np.einsum("spi,spi->s", d, d)).min(initial=np.inf) <= 1e-4 * scale
    return ("vanished" if small else "fail"), K


def _polish(
    prob: _Problem, lam: float, theta: np.ndarray, active: np.ndarray, max_rounds: int = 5
) -> tuple[np.ndarray, float] | None:
    """Solve the TV problem exactly on the ADMM iterate's active set: damped Newton with ``k``
    constant per segment (:func:`_newton_segments`), collapsed jumps dropped, certified by the
    dual ``v_t = sum_{s<=t} 2 (G_s k_s - R_s)``, ``||v_t|| <= lam`` at every inactive ``t``;
    violators that are local maxima of ``||v_t||`` become change points (docs/ltv.md, TV fit).

    :return: ``(theta [T, p, n], max_t ||v_t|| / lam over inactive t)`` or ``None``.
    """
    T, p, n = prob.T, prob.p, prob.n
    q = p * n
    cps = [int(t) for t in np.flatnonzero(active) + 1]
    fscale = float(np.sum(prob.Y**2)) + 1e-300
    theta_init = theta
    for _ in range(max_rounds):
        starts = np.array([0] + cps)
        S = len(starts)
        if S * q**3 > 2e8:
            return None
        seg = _segments(starts, T)
        Gs = np.zeros((S, p, p))
        Rs = np.zeros((S, p, n))
        np.add.at(Gs, seg, prob.G)
        np.add.at(Rs, seg, prob.R)
        counts = np.bincount(seg, minlength=S)[:, None, None]
        K = np.zeros((S, p, n))
        np.add.at(K, seg, theta_init)
        K /= counts
        status, K = _newton_segments(prob, lam, K, Gs, Rs, fscale)
        if status == "fail":
            return None
        if status == "vanished":  # drop the smallest jump (the certificate re-adds it if wrong)
            d = np.diff(K, axis=0)
            norms = np.sqrt(np.einsum("spi,spi->s", d, d))
            drop = int(np.argmin(norms))
            cps = [c for j, c in enumerate(cps) if j != drop]
            theta_init = K[seg]
            continue
        theta_full = K[seg]
        v = np.cumsum(2.0 * (prob.G @ theta_full - prob.R), axis=0)[:-1]  # [T-1, p, n]
        vnorm = np.sqrt(np.einsum("tpi,tpi->t", v, v))
        inactive = np.ones(T - 1, bool)
        inactive[np.array(cps, int) - 1] = False
        ratio = np.where(inactive, vnorm / lam, 0.0)
        worst = int(np.argmax(ratio))
        if ratio[worst] <= 1.0 + 1e-7:
            return theta_full, float(ratio.max())
        # add the violators that are local maxima of ||v_t|| as change points, each new
        # segment kicked in the direction of the dual (the sign of the optimal jump)
        padded = np.concatenate([[0.0], ratio, [0.0]])
        peaks = np.flatnonzero(
            (ratio > 1.0 + 1e-7) & (ratio >= padded[:-2]) & (ratio >= padded[2:])
        )
        cps = sorted(set(cps) | {int(t) + 1 for t in peaks})
        kick_size = 1e-3 * (np.sqrt(np.mean(theta_full**2)) + 1e-300)
        kicks = np.zeros_like(theta_full)
        kicks[peaks + 1] = kick_size * v[peaks] / vnorm[peaks, None, None]
        theta_init = theta_full + np.cumsum(kicks, axis=0)
    return None


def fit_ltv_tv(
    data: object,
    lam: float,
    *,
    affine: bool = False,
    tol: float = 1e-6,
    max_iter: int = 5000,
    rho: float | None = None,
    polish: bool = True,
) -> LTVModel:
    """Piecewise LTV fit for dynamics that jump (contact, payload change)::

        minimize  sum_{t,j} ||x^j_{t+1} - k_t phi^j_t||^2 + lam sum_t ||k_{t+1} - k_t||_F

    by ADMM on ``z_t = k_{t+1} - k_t`` (the ``k``-update the banded solve of :func:`fit_ltv`
    with ``lam^2 = rho / 2``) and a certified Newton polish (docs/ltv.md, "The piecewise (TV) fit").

    :param lam: weight of the group penalty ``>= 0`` (note: ``lam``, not ``lam^2``).
    :param tol: relative tolerance on the primal ``||D k - z||`` and dual
        ``rho ||D^T (z - z_prev)||`` residuals (Boyd et al. 2011, section 3.3).
    :param max_iter: ADMM iteration limit; ``info["converged"]`` tells whether ``tol`` was met
        (or the polish certified optimality).
    :param rho: initial ADMM penalty; default ``2 mean_t tr(G_t) / p``.
    :param polish: try the exact active-set solve (dense, skipped when
        ``segments * p * n > 2500``).
    :return: :class:`LTVModel` with ``info`` = ``{"iterations", "converged", "polished",
        "change_points", "jump_norms" [T-1], "primal_residual", "dual_residual", "kkt_ratio",
        "objective", "rho", "solver", "rss", "noise_var_rows"}`` and ``cov`` that of a
        least-squares fit constant on each detected segment (docs/ltv.md, "The piecewise (TV) fit").
    """
    lam = _check_lam(lam)
    tol = check_positive("tol", tol)
    check_int("max_iter", max_iter, 1)
    prob = _problem(data, affine)
    if rho is not None:
        rho = check_positive("rho", rho)
    if lam == 0.0:
        theta = _l2_model(prob, 0.0, 0.0).params.transpose(0, 2, 1)
        return _tv_model(prob, theta, lam, np.ones(prob.T - 1, bool), iterations=0,
                         converged=True, polished=False, primal=0.0, dual=0.0, kkt_ratio=None,
                         rho=0.0)
    T, p, n = prob.T, prob.p, prob.n
    if rho is None:
        rho = 2.0 * float(np.mean(np.trace(prob.G, axis1=1, axis2=2))) / p
    alpha = 1.6

    def factor(rho_: float) -> np.ndarray:
        try:
            return _cholesky(_band(prob.G, rho_ / 2.0))
        except _NotPositiveDefinite as err:
            msg = _singular_message(prob, float(np.sqrt(rho_ / 2.0)), err.index)
            raise ValueError(msg) from None

    def theta_update(cb: np.ndarray, rho_: float, v: np.ndarray) -> np.ndarray:
        rhs = prob.R + 0.5 * rho_ * _diff_T(v)
        th = _cho_solve_band(cb, rhs.reshape(T * p, n))
        return th.reshape(T, p, n)

    cb = factor(rho)
    theta = theta_update(cb, rho, np.zeros((T - 1, p, n)))  # = the L2 fit with lam^2 = rho/2
    z = np.diff(theta, axis=0)
    w = np.zeros_like(z)  # scaled dual
    theta_scale = np.sqrt(np.mean(theta**2)) + 1e-300
    eps_abs = 1e-3 * tol * theta_scale * np.sqrt(z.size)
    r_norm = s_norm = np.inf
    converged = polished = False
    kkt_ratio = None
    active = np.ones(T - 1, bool)
    stable_since = 0
    tried: set[bytes] = set()
    it = 0
    for it in range(1, max_iter + 1):
        theta = theta_update(cb, rho, z - w)
        Dth = np.diff(theta, axis=0)
        Dth_hat = alpha * Dth + (1.0 - alpha) * z
        z_old = z
        z = _group_shrink(Dth_hat + w, lam / rho)
        w = w + Dth_hat - z
        r_norm = float(np.linalg.norm(Dth - z))
        s_norm = float(rho * np.linalg.norm(_diff_T(z - z_old)))
        eps_pri = eps_abs + tol * max(np.linalg.norm(Dth), np.linalg.norm(z))
        eps_dual = eps_abs * rho + tol * rho * np.linalg.norm(_diff_T(w))
        new_active = np.einsum("tpi,tpi->t", z, z) > 0.0
        if not np.array_equal(new_active, active):
            active, stable_since = new_active, it
        converged = r_norm <= eps_pri and s_norm <= eps_dual
        # polish at convergence, or once the active set has been stable for 50 iterations
        if polish and (converged or (it - stable_since >= 50 and active.tobytes() not in tried)):
            tried.add(active.tobytes())
            res = _polish(prob, lam, theta, active)
            if res is not None:
                theta, kkt_ratio = res
                converged = polished = True
        if converged:
            break
        if it % 10 == 0:
            r_rel, s_rel = r_norm / eps_pri, s_norm / eps_dual
            if r_rel > 10.0 * s_rel or s_rel > 10.0 * r_rel:
                change = 2.0 if r_rel > s_rel else 0.5
                rho *= change
                w /= change
                cb = factor(rho)
    if not converged:
        warnings.warn(
            f"fit_ltv_tv did not reach tol={tol:g} in {max_iter} iterations "
            f"(primal {r_norm:.3g}, dual {s_norm:.3g})",
            RuntimeWarning,
            stacklevel=2,
        )
    if polished:
        dth = np.diff(theta, axis=0)
        active = np.einsum("tpi,tpi->t", dth, dth) > 0.0
    return _tv_model(prob, theta, lam, active, iterations=it, converged=converged,
                     polished=polished, primal=r_norm, dual=s_norm, kkt_ratio=kkt_ratio, rho=rho)


def _tv_model(
    prob: _Problem, theta: np.ndarray, lam: float, active: np.ndarray, *, iterations: int,
    converged: bool, polished: bool, primal: float, dual: float, kkt_ratio: float | None,
    rho: float,
) -> LTVModel:
    """Wrap a TV solution: segment-wise least-squares covariance and diagnostics (the solver's
    iteration count, convergence, residuals and penalty ``rho`` go into ``info``)."""
    T, p = prob.T, prob.p
    seg = _segments(np.concatenate([[0], np.flatnonzero(active) + 1]), T)
    n_seg = int(seg[-1]) + 1
    Gseg = np.zeros((n_seg, p, p))
    np.add.at(Gseg, seg, prob.G)
    eps = 1e-10 * np.trace(Gseg, axis1=1, axis2=2)[:, None, None] / p + 1e-300
    Sigma_seg = np.linalg.inv(Gseg + eps * np.eye(p))
    resid = prob.Y - np.einsum("jtp,tpi->jti", prob.Phi, theta)
    rss = np.einsum("jti,jti->i", resid, resid)
    noise_rows = rss / max(prob.M - p * n_seg, 1)
    cov = noise_rows[None, :, None, None] * Sigma_seg[seg][:, None]
    A, B, c = _split_theta(theta, prob.n, prob.m, prob.affine)
    dth = np.diff(theta, axis=0)
    info = {
        "solver": "admm+newton" if polished else "admm",
        "iterations": int(iterations),
        "converged": bool(converged),
        "polished": bool(polished),
        "change_points": [int(t) for t in np.flatnonzero(active) + 1] if lam > 0 else [],
        "jump_norms": np.sqrt(np.einsum("tpi,tpi->t", dth, dth)),
        "primal_residual": float(primal),
        "dual_residual": float(dual),
        "kkt_ratio": kkt_ratio,
        "objective": _tv_objective(prob, theta, lam),
        "rho": float(rho),
        "rss": rss,
        "noise_var_rows": noise_rows,
    }
    return LTVModel(A, B, c, cov, lam=lam, noise_var=float(np.mean(noise_rows)), info=info)


# --------------------------------------------------------------------------------------------
# Prior fusion
# --------------------------------------------------------------------------------------------


def fuse_prior(
    model: LTVModel,
    A_prior: np.ndarray,
    B_prior: np.ndarray,
    cov_prior: np.ndarray,
    *,
    c_prior: np.ndarray | None = None,
) -> LTVModel:
    """Fuse the fit with an independent Gaussian prior on the Jacobians, per time step and per
    output row (a Kalman update, ``H`` selecting ``[A B (c)]``; docs/ltv.md, "Prior fusion").

    :param model: a fitted :class:`LTVModel` (its ``cov`` is in absolute units).
    :param A_prior: ``[T, n, n]`` prior means, e.g. the NN ensemble's Jacobians.
    :param B_prior: ``[T, n, m]``.
    :param cov_prior: ``[T, n, q, q]`` per-output-row covariance blocks or ``[T, n, q]``
        diagonal variances, ``q = n + m`` or, with ``c_prior``, ``n + m + 1``. Must be
        positive definite.
    :param c_prior: ``[T, n]`` prior mean of the affine term (affine models only).
    :return: a new :class:`LTVModel`; ``info["fused_prior"] = True``.
    """
    if not isinstance(model, LTVModel):
        raise TypeError(f"model must be an LTVModel, got {type(model).__name__}")
    T, n, m = model.T, model.state_dim, model.action_dim
    A_prior = as_array("A_prior", A_prior, (T, n, n))
    B_prior = as_array("B_prior", B_prior, (T, n, m))
    means = [A_prior, B_prior]
    if c_prior is not None:
        if not model.affine:
            raise ValueError("c_prior given but the model has no affine term")
        means.append(as_array("c_prior", c_prior, (T, n))[:, :, None])
    q = n + m + (c_prior is not None)
    k_prior = np.concatenate(means, axis=2)  # [T, n, q]
    cov_prior = as_array("cov_prior", cov_prior)
    if cov_prior.shape == (T, n, q):
        if np.any(cov_prior <= 0):
            raise ValueError("cov_prior: diagonal variances must be > 0")
        P_prior = cov_prior[..., None] * np.eye(q)
    elif cov_prior.shape == (T, n, q, q):
        P_prior = cov_prior
        if not np.allclose(P_prior, P_prior.transpose(0, 1, 3, 2), rtol=1e-10, atol=0.0):
            raise ValueError("cov_prior: blocks must be symmetric")
        if np.any(np.linalg.eigvalsh(P_prior) <= 0):
            raise ValueError("cov_prior: blocks must be positive definite")
    else:
        raise ValueError(
            f"cov_prior must have shape [T, n, q, q] or [T, n, q] = [{T}, {n}, {q}(, {q})], "
            f"got {list(cov_prior.shape)}"
        )
    k = model.params  # [T, n, p]
    P = np.asarray(model.cov)  # [T, n, p, p]
    PHt = P[..., :, :q]  # P H^T      [T, n, p, q]
    S = P[..., :q, :q] + P_prior  # H P H^T + P_prior
    K = np.linalg.solve(S, PHt.transpose(0, 1, 3, 2)).transpose(0, 1, 3, 2)  # [T, n, p, q]
    innov = k_prior - k[..., :q]
    k_new = k + np.einsum("tipq,tiq->tip", K, innov)
    P_new = P - K @ PHt.transpose(0, 1, 3, 2)
    P_new = 0.5 * (P_new + P_new.transpose(0, 1, 3, 2))
    A, B, c = _split_theta(k_new.transpose(0, 2, 1), n, m, model.affine)
    info = dict(model.info)
    info["fused_prior"] = True
    return LTVModel(A, B, c, P_new, lam=model.lam, noise_var=model.noise_var, info=info)

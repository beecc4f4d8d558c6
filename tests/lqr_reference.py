"""The numpy reference of iLQR's backward pass and box QP, which the compiled kernels
(:mod:`mbtsr._lqr_kernels`) are tested against: the augmented quadratic ``z = [1; dx; du]``,
``M_t = L_t + F_t^T V_{t+1} F_t`` with ``F_t = [[1, 0, 0], [0, A_t, B_t]]``, one LAPACK ``dposv``
for ``[k_t, K_t] = -Quu_reg^-1 [Qu, Qux_reg]``, ``V_t = G_t^T M_t G_t`` with
``G_t = [[I], [k_t, K_t]]`` (the unregularised ``Quu, Qux`` enter the value update, as in Tassa
et al.). Written separately from the kernels, in plain numpy; it was the solver's own code
before the kernels replaced it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

from mbtsr.dynamics import LinearDynamics
from mbtsr.ilqr import ILQROptions


@dataclass
class _LQProblem:
    """The local LQ problem around a nominal trajectory in augmented form (see module doc).

    ``F: [T, 1+n, 1+n+m]`` and ``FT`` = ``F_t^T``; ``L: [T, 1+n+m, 1+n+m]`` stage cost quadratics;
    ``VT: [1+n, 1+n]`` terminal value; ``lo, hi: [T, m]`` bounds on ``du``;
    ``BB: [T, m, m]``, ``BA: [T, m, 1+n]`` for state regularisation (reg_type 2).
    """

    FT: np.ndarray
    F: np.ndarray
    L: np.ndarray
    VT: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    reg_type: int
    BB: np.ndarray | None
    BA: np.ndarray | None

    @classmethod
    def build(cls, A, B, derivs, U, lower, upper, reg_type) -> _LQProblem:
        T, n, m = B.shape
        nz = 1 + n
        lx, lu, lxx, luu, lux = derivs
        F = np.zeros((T, nz, nz + m))
        F[:, 0, 0] = 1.0
        F[:, 1:, 1:nz] = A
        F[:, 1:, nz:] = B
        L = np.zeros((T, nz + m, nz + m))
        L[:, 0, 1:nz] = lx[:-1]
        L[:, 1:nz, 0] = lx[:-1]
        L[:, 0, nz:] = lu
        L[:, nz:, 0] = lu
        L[:, 1:nz, 1:nz] = lxx[:-1]
        L[:, nz:, nz:] = luu
        L[:, nz:, 1:nz] = lux
        L[:, 1:nz, nz:] = lux.transpose(0, 2, 1)
        VT = np.zeros((nz, nz))
        VT[0, 1:] = lx[-1]
        VT[1:, 0] = lx[-1]
        VT[1:, 1:] = lxx[-1]
        BB = BA = None
        if reg_type == 2:
            Bt = B.transpose(0, 2, 1)
            BB = Bt @ B
            BA = np.zeros((T, m, nz))
            BA[:, :, 1:] = Bt @ A
        return cls(
            FT=np.ascontiguousarray(F.transpose(0, 2, 1)),
            F=F,
            L=L,
            VT=VT,
            lo=lower[None] - U,
            hi=upper[None] - U,
            reg_type=reg_type,
            BB=BB,
            BA=BA,
        )


def _backward_pass(p: _LQProblem, lam: float, has_limits: bool, opts: ILQROptions):
    """Riccati-like recursion over t = T-1..0 on the augmented quadratic.

    :return: ``(k [T, m], K [T, m, n], dV1, dV2)`` or ``None`` if some regularised ``Quu`` is
        not positive definite (or the recursion produced non-finite numbers).
    """
    T, nzm, nz = p.FT.shape
    m = nzm - nz
    kK = np.zeros((T, m, nz))  # [k_t, K_t] stacked
    Ms = np.empty((T, nzm, nzm))
    G = np.zeros((nzm, nz))
    G[:nz, :nz] = np.eye(nz)
    lam_I = lam * np.eye(m)
    V = p.VT
    k_warm = np.zeros(m)
    dposv = lapack.dposv
    # bounds as Python lists: comparing m floats in Python is ~10x cheaper than numpy calls
    lo_list, hi_list = (p.lo.tolist(), p.hi.tolist()) if has_limits else (None, None)
    FT_all, F_all, L_all = p.FT, p.F, p.L
    matmul = np.matmul
    for t in range(T - 1, -1, -1):
        M = Ms[t]
        matmul(FT_all[t] @ V, F_all[t], out=M)
        M += L_all[t]
        if p.reg_type == 1:
            H = M[nz:, nz:] + lam_I
            rhs = M[nz:, :nz]
        else:
            H = M[nz:, nz:] + lam * p.BB[t]
            rhs = M[nz:, :nz] + lam * p.BA[t]
        _, sol, info = dposv(H, rhs)
        if info != 0:
            return None
        gains = -sol
        if has_limits and _outside(gains[:, 0].tolist(), lo_list[t], hi_list[t]):
            kt, free, ok = _active_set_guess(H, rhs[:, 0], gains[:, 0], p.lo[t], p.hi[t])
            if not ok:
                kt, free, ok = _box_qp(H, rhs[:, 0], p.lo[t], p.hi[t], k_warm, opts)
            if not ok:
                return None
            gains = np.zeros((m, nz))
            gains[:, 0] = kt
            if free.any():
                _, solf, info = dposv(H[free][:, free], rhs[free, 1:])
                if info != 0:
                    return None
                gains[free, 1:] = -solf
        kK[t] = gains
        k_warm = gains[:, 0]
        G[nz:] = gains
        V = G.T @ M @ G
        V = 0.5 * (V + V.T)
    k, K = kK[:, :, 0], kK[:, :, 1:]
    if not (np.isfinite(kK).all() and np.isfinite(V).all()):
        return None
    Qu, Quu = Ms[:, nz:, 0], Ms[:, nz:, nz:]
    dV1 = float(np.einsum("ti,ti->", k, Qu))
    dV2 = 0.5 * float(np.einsum("ti,tij,tj->", k, Quu, k))
    return np.ascontiguousarray(k), np.ascontiguousarray(K), dV1, dV2


def _outside(k: list, lo: list, hi: list) -> bool:
    """Whether any ``k_j`` lies outside ``[lo_j, hi_j]`` (NaN counts as outside)."""
    for a, b, c in zip(k, lo, hi):
        if not b <= a <= c:
            return True
    return False


def _active_set_guess(H, g, x_free, lower, upper):
    """Cheap first try at the box-QP ``min 0.5 x^T H x + g^T x, lower <= x <= upper``.

    Clamp the dimensions where the unconstrained minimiser ``x_free`` leaves the box, re-solve
    for the others and accept if the KKT conditions hold (free part inside the box, gradient
    pointing out of the box on clamped dimensions). For small ``m`` this is usually right; it
    runs on Python floats (``m`` is 1-4 here, where numpy's per-call overhead dominates) with
    one LAPACK solve if more than one dimension stays free. Otherwise :func:`_box_qp` runs.

    :return: ``(x [m], free [m] bool, ok)``.
    """
    Hl, gl = H.tolist(), g.tolist()
    lo, hi = lower.tolist(), upper.tolist()
    x = [min(max(a, b), c) for a, b, c in zip(x_free.tolist(), lo, hi)]
    free = [a == b for a, b in zip(x, x_free.tolist())]
    fi = [i for i, f in enumerate(free) if f]
    ci = [i for i, f in enumerate(free) if not f]
    if fi:
        rhs = [gl[i] + sum(Hl[i][j] * x[j] for j in ci) for i in fi]
        if len(fi) == 1:
            h = Hl[fi[0]][fi[0]]
            if not h > 0:
                return np.array(x), np.array(free), False
            sol = [rhs[0] / h]
        else:
            _, sol_arr, info = lapack.dposv(H[np.ix_(fi, fi)], np.array(rhs))
            if info != 0:
                return np.array(x), np.array(free), False
            sol = sol_arr.tolist()
        for i, v in zip(fi, sol):
            x[i] = -v
            if not lo[i] <= x[i] <= hi[i]:
                return np.array(x), np.array(free), False
    ok = True
    for i in ci:
        if lo[i] == hi[i]:  # a fixed dimension is clamped whatever its gradient
            continue
        grad = gl[i] + sum(Hl[i][j] * x[j] for j in range(len(x)))
        if (x[i] <= lo[i] and grad < 0) or (x[i] >= hi[i] and grad > 0):
            ok = False
            break
    return np.array(x), np.array(free), ok


def _box_qp(H, g, lower, upper, x0, opts: ILQROptions):
    """Projected-Newton solution of ``min 0.5 x^T H x + g^T x`` s.t. ``lower <= x <= upper``.

    Bertsekas' projected Newton as used by Tassa et al. 2014 (``boxQP``), warm-started at
    ``x0``. ``H: [m, m]`` positive definite on the free set, ``g, lower, upper, x0: [m]``.

    :return: ``(x [m], free [m] bool, ok)``; ``free`` marks the unclamped dimensions at the
        solution; ``ok`` is False if the free Hessian block is not positive definite.
    """
    x = np.clip(x0, lower, upper)
    value = x @ g + 0.5 * x @ H @ x
    dposv = lapack.dposv
    for it in range(opts.boxqp_max_iter):
        grad = g + H @ x
        clamped = ((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0))
        free = ~clamped
        if clamped.all():
            break
        if np.linalg.norm(grad[free]) < opts.boxqp_min_grad:
            break
        grad_clamped = g + H @ (x * clamped)
        _, sol, info = dposv(H[free][:, free], grad_clamped[free])
        if info != 0:
            return x, free, False
        search = np.zeros_like(x)
        search[free] = -sol - x[free]
        sdotg = search @ grad
        if sdotg >= 0:  # no descent direction left: at the optimum up to round-off
            break
        step = 1.0
        xc = np.clip(x + step * search, lower, upper)
        vc = xc @ g + 0.5 * xc @ H @ xc
        while (vc - value) / (step * sdotg) < opts.boxqp_armijo:
            step *= opts.boxqp_step_dec
            if step < opts.boxqp_min_step:
                break
            xc = np.clip(x + step * search, lower, upper)
            vc = xc @ g + 0.5 * xc @ H @ xc
        improvement = value - vc
        x, value = xc, vc
        if it > 0 and improvement < opts.boxqp_min_rel_improve * abs(value):
            break
    grad = g + H @ x
    clamped = ((x <= lower) & (grad > 0)) | ((x >= upper) & (grad < 0))
    return x, ~clamped, True


class NaNOffNominal:
    """A linear model that returns NaN as soon as any control differs from 0, or, with
    ``beyond``, wherever the next state's largest ``|x_i|`` exceeds it."""

    def __init__(self, A, B, beyond: float | None = None):
        self.lin = LinearDynamics(A, B)
        self.state_dim, self.action_dim = B.shape
        self.beyond = beyond

    def step(self, x, u, t=None):
        out = self.lin.step(x, u)
        if self.beyond is None:
            out[np.any(u != 0, axis=-1)] = np.nan
        else:
            out[np.abs(out).max(axis=-1) > self.beyond] = np.nan
        return out

    def jacobians(self, x, u, t=0):
        return self.lin.jacobians(x, u)

"""Compiled (numba) kernels of the control-limited iLQR backward pass.

Pure functions on float64 arrays; ``mbtsr.ilqr`` calls :func:`backward_pass` once per backward
pass (one compiled call for the whole horizon, no Python per time step). The numpy recursion in
``tests/lqr_reference.py`` (augmented form, LAPACK ``dposv``) is the reference the tests
compare against.

Per time step ``t = T-1 .. 0`` with the value ``(v_x, V_xx)`` of step ``t+1``::

    Q_x  = l_x  + A^T v_x            Q_u  = l_u  + B^T v_x
    Q_xx = l_xx + A^T V_xx A         Q_uu = l_uu + B^T V_xx B      Q_ux = l_ux + B^T V_xx A
    reg_type 1:  H = Q_uu + lam I,          R = Q_ux
    reg_type 2:  H = Q_uu + lam B^T B,      R = Q_ux + lam B^T A      (lam I added to V_xx)
    k = argmin_{lo <= k <= hi} 0.5 k^T H k + Q_u^T k                 (box QP)
    K[free] = -H[free, free]^-1 R[free],   K[clamped] = 0
    v_x  = Q_x  + K^T Q_uu k + K^T Q_u + Q_ux^T k
    V_xx = Q_xx + K^T Q_uu K + K^T Q_ux + Q_ux^T K                   (symmetrised)

The box QP: the unconstrained minimiser if it lies in the box, else an active-set guess checked
by its KKT conditions, else Bertsekas' projected Newton (Tassa et al. 2014 ``boxQP``)
warm-started at ``k_{t+1}``. ``numba.njit(cache=True)``; why numba, and the compile time:
docs/ilqr.md, "Performance".
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["backward_pass", "BOXQP_DEFAULTS"]

#: (max_iter, min_grad, min_rel_improve, step_dec, min_step, armijo): Tassa et al.'s boxQP,
#: all floats (one compiled signature).
BOXQP_DEFAULTS = (100.0, 1e-8, 1e-8, 0.6, 1e-22, 0.1)


@njit(cache=True)
def _chol(H, idx, nf, L):
    """Cholesky ``L L^T`` of ``H[idx[:nf]][:, idx[:nf]]`` into ``L[:nf, :nf]``; False if not PD."""
    for i in range(nf):
        for j in range(i + 1):
            s = H[idx[i], idx[j]]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if not s > 0.0:  # also catches NaN
                    return False
                L[i, i] = np.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    return True


@njit(cache=True)
def _chol_solve(L, nf, b):
    """Solve ``L L^T x = b`` in place for ``b[:nf]``."""
    for i in range(nf):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * b[k]
        b[i] = s / L[i, i]
    for i in range(nf - 1, -1, -1):
        s = b[i]
        for k in range(i + 1, nf):
            s -= L[k, i] * b[k]
        b[i] = s / L[i, i]


@njit(cache=True)
def _atb(X, Y, base, out):
    """``out = base + X^T Y``: ``X [a, p]``, ``Y [a, q]``, ``base, out [p, q]`` (``X.T`` of a
    view gives ``X Y``); BLAS from 2^18 multiply-adds (a state of about 64), loops below."""
    if X.shape[0] * X.shape[1] * Y.shape[1] >= 262144:
        out[:] = base + np.dot(X.T, Y)
        return
    for i in range(X.shape[1]):
        for j in range(Y.shape[1]):
            s = base[i, j]
            for a in range(X.shape[0]):
                s += X[a, i] * Y[a, j]
            out[i, j] = s


@njit(cache=True)
def _atv(X, v, base, out):
    """``out = base + X^T v``: ``X [a, p]``, ``v [a]``, ``base, out [p]``."""
    for i in range(X.shape[1]):
        s = base[i]
        for a in range(X.shape[0]):
            s += X[a, i] * v[a]
        out[i] = s


@njit(cache=True)
def _qp_value(H, g, x):
    m = x.shape[0]
    v = 0.0
    for i in range(m):
        hx = 0.0
        for j in range(m):
            hx += H[i, j] * x[j]
        v += x[i] * (g[i] + 0.5 * hx)
    return v


@njit(cache=True)
def _free_newton(H, g, x, free, idx, nf, L, b):
    """Newton step on the free set ``idx[:nf]`` with the clamped part of ``x`` fixed: ``b[:nf]``
    becomes ``-x[free]`` of the minimiser; False if ``H[free, free]`` is not positive definite."""
    for a in range(nf):
        i = idx[a]
        s = g[i]
        for j in range(g.shape[0]):
            if not free[j]:
                s += H[i, j] * x[j]
        b[a] = s
    if not _chol(H, idx, nf, L):
        return False
    _chol_solve(L, nf, b)
    return True


@njit(cache=True)
def _active_set_guess(H, g, x_free, lo, hi, x, free, L, idx, b):
    """Clamp where the unconstrained minimiser leaves the box, re-solve the rest, check KKT.

    Writes ``x [m]`` and ``free [m]``; returns whether the KKT conditions hold.
    """
    m = g.shape[0]
    nf = 0
    for i in range(m):
        x[i] = min(max(x_free[i], lo[i]), hi[i])
        free[i] = x[i] == x_free[i]
        if free[i]:
            idx[nf] = i
            nf += 1
    if nf > 0:
        if not _free_newton(H, g, x, free, idx, nf, L, b):
            return False
        for a in range(nf):
            i = idx[a]
            x[i] = -b[a]
            if not (lo[i] <= x[i] <= hi[i]):
                return False
    for i in range(m):
        if free[i] or lo[i] == hi[i]:  # a fixed dimension is clamped whatever its gradient
            continue
        grad = g[i]
        for j in range(m):
            grad += H[i, j] * x[j]
        if (x[i] <= lo[i] and grad < 0) or (x[i] >= hi[i] and grad > 0):
            return False
    return True


@njit(cache=True)
def _box_qp(H, g, lo, hi, x0, x, free, L, idx, b, prm):
    """Projected Newton for ``min 0.5 x^T H x + g^T x, lo <= x <= hi`` (warm start ``x0``).

    Writes ``x`` and ``free``; returns False if a free Hessian block is not positive definite.
    ``prm = (max_iter, min_grad, min_rel_improve, step_dec, min_step, armijo)``.
    """
    m = g.shape[0]
    max_iter, min_grad, min_rel, step_dec, min_step, armijo = prm
    grad = np.empty(m)
    search = np.empty(m)
    xc = np.empty(m)
    for i in range(m):
        x[i] = min(max(x0[i], lo[i]), hi[i])
    value = _qp_value(H, g, x)
    for it in range(int(max_iter)):
        _atv(H.T, x, g, grad)  # the gradient g + H x
        nf = 0
        gnorm2 = 0.0
        for i in range(m):
            clamped = (x[i] <= lo[i] and grad[i] > 0) or (x[i] >= hi[i] and grad[i] < 0)
            free[i] = not clamped
            if free[i]:
                idx[nf] = i
                nf += 1
                gnorm2 += grad[i] * grad[i]
        if nf == 0:
            break
        if np.sqrt(gnorm2) < min_grad:
            break
        # Newton step on the free set with the clamped part fixed
        if not _free_newton(H, g, x, free, idx, nf, L, b):
            return False
        for i in range(m):
            search[i] = 0.0
        for a in range(nf):
            i = idx[a]
            search[i] = -b[a] - x[i]
        sdotg = 0.0
        for i in range(m):
            sdotg += search[i] * grad[i]
        if sdotg >= 0:  # no descent direction left: at the optimum up to round-off
            break
        step = 1.0
        for i in range(m):
            xc[i] = min(max(x[i] + step * search[i], lo[i]), hi[i])
        vc = _qp_value(H, g, xc)
        while (vc - value) / (step * sdotg) < armijo:
            step *= step_dec
            if step < min_step:
                break
            for i in range(m):
                xc[i] = min(max(x[i] + step * search[i], lo[i]), hi[i])
            vc = _qp_value(H, g, xc)
        improvement = value - vc
        for i in range(m):
            x[i] = xc[i]
        value = vc
        if it > 0 and improvement < min_rel * abs(value):
            break
    _atv(H.T, x, g, grad)  # the gradient g + H x
    for i in range(m):
        free[i] = not ((x[i] <= lo[i] and grad[i] > 0) or (x[i] >= hi[i] and grad[i] < 0))
    return True


@njit(cache=True)
def backward_pass(A, B, lx, lu, lxx, luu, lux, lo, hi, lam, reg_type, has_limits, prm):
    """Control-limited iLQR backward pass over the whole horizon (see the module doc).

    :param A: ``[T, n, n]``; ``B: [T, n, m]`` dynamics Jacobians.
    :param lx: ``[T+1, n]``; ``lu: [T, m]``; ``lxx: [T+1, n, n]``; ``luu: [T, m, m]``;
        ``lux: [T, m, n]`` cost derivatives (last rows of ``lx, lxx``: terminal cost).
    :param lo, hi: ``[T, m]`` bounds on the control step ``du`` (``u_min - U``, ``u_max - U``).
    :param lam: regularisation; ``reg_type``: 1 (``Quu + lam I``) or 2 (``V_xx + lam I``).
    :param has_limits: False skips every bound check (unbounded problem).
    :param prm: box-QP settings, as :data:`BOXQP_DEFAULTS`.
    :return: ``(ok, k [T, m], K [T, m, n], dV1, dV2)``; ``ok`` is False when some regularised
        ``Quu`` is not positive definite or the recursion produced non-finite numbers.
    """
    T, n, m = B.shape
    k = np.zeros((T, m))
    K = np.zeros((T, m, n))
    vx = lx[T].copy()
    Vxx = lxx[T].copy()
    Qx = np.empty(n)
    Qu = np.empty(m)
    Qxx = np.empty((n, n))
    Quu = np.empty((m, m))
    Qux = np.empty((m, n))
    H = np.empty((m, m))
    R = np.empty((m, n))
    VA = np.empty((n, n))
    VB = np.empty((n, m))
    L = np.empty((m, m))
    idx = np.empty(m, dtype=np.int64)
    b = np.empty(m)
    kt = np.empty(m)
    k_free = np.empty(m)
    k_warm = np.zeros(m)
    free = np.empty(m, dtype=np.bool_)
    QuuK = np.empty((m, n))
    BB = np.empty((m, m))
    BA = np.empty((m, n))
    zero_nn, zero_nm, zero_mm, zero_mn = (np.zeros((n, n)), np.zeros((n, m)), np.zeros((m, m)),
                                          np.zeros((m, n)))
    dV1 = 0.0
    dV2 = 0.0
    for t in range(T - 1, -1, -1):
        At, Bt = A[t], B[t]
        _atb(Vxx.T, At, zero_nn, VA)  # V A
        _atb(Vxx.T, Bt, zero_nm, VB)  # V B
        _atv(At, vx, lx[t], Qx)
        _atb(At, VA, lxx[t], Qxx)
        _atv(Bt, vx, lu[t], Qu)
        _atb(Bt, VB, luu[t], Quu)
        _atb(Bt, VA, lux[t], Qux)
        # regularisation
        H[:] = Quu
        R[:] = Qux
        if reg_type == 1:
            for i in range(m):
                H[i, i] += lam
        else:
            _atb(Bt, Bt, zero_mm, BB)
            _atb(Bt, At, zero_mn, BA)
            H += lam * BB
            R += lam * BA
        # unconstrained step
        for i in range(m):
            idx[i] = i
        if not _chol(H, idx, m, L):
            return False, k, K, 0.0, 0.0
        for i in range(m):
            b[i] = Qu[i]
        _chol_solve(L, m, b)
        inside = True
        for i in range(m):
            kt[i] = -b[i]
            free[i] = True
            if has_limits and not (lo[t, i] <= kt[i] <= hi[t, i]):
                inside = False
        if inside:
            for j in range(n):
                for i in range(m):
                    b[i] = R[i, j]
                _chol_solve(L, m, b)
                for i in range(m):
                    K[t, i, j] = -b[i]
        else:
            for i in range(m):
                k_free[i] = kt[i]
            ok = _active_set_guess(H, Qu, k_free, lo[t], hi[t], kt, free, L, idx, b)
            if not ok:
                ok = _box_qp(H, Qu, lo[t], hi[t], k_warm, kt, free, L, idx, b, prm)
            if not ok:
                return False, k, K, 0.0, 0.0
            nf = 0
            for i in range(m):
                if free[i]:
                    idx[nf] = i
                    nf += 1
            if nf > 0:
                if not _chol(H, idx, nf, L):
                    return False, k, K, 0.0, 0.0
                for j in range(n):
                    for a in range(nf):
                        b[a] = R[idx[a], j]
                    _chol_solve(L, nf, b)
                    for a in range(nf):
                        K[t, idx[a], j] = -b[a]
        for i in range(m):
            k[t, i] = kt[i]
            k_warm[i] = kt[i]
        # value update with the unregularised Q terms
        Kt = K[t]
        _atb(Quu.T, Kt, zero_mn, QuuK)  # Quu K
        for i in range(n):
            s = Qx[i]
            for a in range(m):
                s += QuuK[a, i] * kt[a] + Kt[a, i] * Qu[a] + Qux[a, i] * kt[a]
            vx[i] = s
        for i in range(n):
            for j in range(i, n):
                s = Qxx[i, j]
                for a in range(m):
                    s += Kt[a, i] * QuuK[a, j] + Kt[a, i] * Qux[a, j] + Qux[a, i] * Kt[a, j]
                s2 = Qxx[j, i]
                for a in range(m):
                    s2 += Kt[a, j] * QuuK[a, i] + Kt[a, j] * Qux[a, i] + Qux[a, j] * Kt[a, i]
                Vxx[i, j] = 0.5 * (s + s2)
                Vxx[j, i] = Vxx[i, j]
        for i in range(m):
            dV1 += kt[i] * Qu[i]
            s = 0.0
            for j in range(m):
                s += Quu[i, j] * kt[j]
            dV2 += 0.5 * kt[i] * s
    if not (_finite_flat(k.ravel()) and _finite_flat(K.ravel()) and _finite_flat(vx)
            and _finite_flat(Vxx.ravel())):
        return False, k, K, 0.0, 0.0
    return True, k, K, dV1, dV2


@njit(cache=True)
def policy_row(U, k, K, X, t, alpha, lower, upper, x, u_out):  # pragma: no cover - compiled
    """``u_out[m] = clip(U_t + alpha k_t + K_t (x - X_t), lower, upper)``: one step of iLQR's
    line-search policy for one rollout (shared by the compiled rollouts)."""
    m, n = K.shape[1], K.shape[2]
    for j in range(m):
        v = U[t, j] + alpha * k[t, j]
        for i in range(n):
            v += K[t, j, i] * (x[i] - X[t, i])
        u_out[j] = min(max(v, lower[j]), upper[j])


@njit(cache=True)
def guard_row(x_next, x_nominal, biggest):  # pragma: no cover - compiled
    """A non-finite ``x_next [n]`` is replaced by ``x_nominal`` (so the model never sees NaN).

    :return: ``(finite, max(biggest, max |x_next|))``: whether the row stays alive, and the
        running largest magnitude of the rollout (shared by the compiled rollouts)."""
    finite = True
    for i in range(x_next.shape[0]):
        if not np.isfinite(x_next[i]):
            finite = False
    if not finite:
        for i in range(x_next.shape[0]):
            x_next[i] = x_nominal[i]
    for i in range(x_next.shape[0]):
        biggest = max(biggest, abs(x_next[i]))
    return finite, biggest


@njit(cache=True)
def rollout_buffers(x0, T, m, N):  # pragma: no cover - compiled
    """``(Xn [N, T+1, n], Un [N, T, m], alive [N])`` of ``N`` rollouts, ``Xn[:, 0] = x0``."""
    n = x0.shape[0]
    Xn = np.empty((N, T + 1, n))
    for a in range(N):
        for i in range(n):
            Xn[a, 0, i] = x0[i]
    return Xn, np.empty((N, T, m)), np.ones(N, dtype=np.bool_)


@njit(cache=True)
def rollout_policy_affine(A, B, c, x0, X, U, k, K, alphas, lower, upper, max_norm):
    """Closed-loop rollouts of an affine model for all step sizes, in one compiled call.

    Model ``x_{t+1} = A_t x_t + B_t u_t + c_t`` with ``A: [TA, n, n]``, ``B: [TA, n, m]``,
    ``c: [TA, n]`` (``TA = 1``: time-invariant, else ``TA >= T``: row ``t``). Policy
    ``u_t = clip(U_t + alpha k_t + K_t (x_t - X_t), lower, upper)``; ``X: [T+1, n]``,
    ``U, k: [T, m]``, ``K: [T, m, n]``, ``alphas: [N]``, ``lower, upper: [m]``.
    Same semantics as ``mbtsr.ilqr._rollout_policy``: a row that turns non-finite is dead and
    continues from the nominal state; rows exceeding ``max_norm`` are dead at the end.

    :return: ``(Xn [N, T+1, n], Un [N, T, m], alive [N])``.
    """
    T, m = U.shape
    n = x0.shape[0]
    TA = A.shape[0]
    Xn, Un, alive = rollout_buffers(x0, T, m, alphas.shape[0])
    for a in range(alphas.shape[0]):
        biggest = 0.0
        for t in range(T):
            s = t if TA > 1 else 0
            policy_row(U, k, K, X, t, alphas[a], lower, upper, Xn[a, t], Un[a, t])
            for i in range(n):
                v = c[s, i]
                for j in range(n):
                    v += A[s, i, j] * Xn[a, t, j]
                for j in range(m):
                    v += B[s, i, j] * Un[a, t, j]
                Xn[a, t + 1, i] = v
            finite, biggest = guard_row(Xn[a, t + 1], X[t + 1], biggest)
            alive[a] &= finite
        if not biggest <= max_norm:
            alive[a] = False
        for i in range(n):
            if not abs(x0[i]) <= max_norm:
                alive[a] = False
    return Xn, Un, alive


@njit(cache=True)
def policy_controls(Xn, X, U, k, alphas, K, t, lower, upper, Un):  # pragma: no cover - compiled
    """``Un[a, t] = clip(U_t + alphas[a] k_t + K_t (Xn[a, t] - X_t), lower, upper)`` for all
    rows ``a`` (``Xn: [N, T+1, n]``, ``Un: [N, T, m]``, written): one call per time step of
    the generic closed-loop rollout, instead of six numpy calls."""
    m, n = K.shape[1], K.shape[2]
    for a in range(Xn.shape[0]):  # policy_row's arithmetic, without its views (faster)
        for j in range(m):
            v = U[t, j] + alphas[a] * k[t, j]
            for i in range(n):
                v += K[t, j, i] * (Xn[a, t, i] - X[t, i])
            Un[a, t, j] = min(max(v, lower[j]), upper[j])


@njit(cache=True)
def _finite_flat(a):  # pragma: no cover - compiled
    for v in a:
        if not np.isfinite(v):
            return False
    return True


@njit(cache=True)
def all_finite(A, B, lx, lu, lxx, luu, lux):  # pragma: no cover - compiled
    """True when every entry of the (C-contiguous) Jacobians and cost derivatives is finite."""
    return (_finite_flat(A.ravel()) and _finite_flat(B.ravel()) and _finite_flat(lx.ravel())
            and _finite_flat(lu.ravel()) and _finite_flat(lxx.ravel())
            and _finite_flat(luu.ravel()) and _finite_flat(lux.ravel()))


@njit(cache=True)
def grad_norm(k, U):  # pragma: no cover - compiled
    """``mean_t max_j |k_tj| / (|U_tj| + 1)`` of ``k, U [T, m]`` (iLQR's gradient measure)."""
    T, m = k.shape
    total = 0.0
    for t in range(T):
        best = -np.inf
        for j in range(m):
            best = max(best, abs(k[t, j]) / (abs(U[t, j]) + 1.0))
        total += best
    return total / T

"""CasADi-assisted trajectory costs for iLQR, MPC and the IPOPT reference.

``J(X [T+1, n], U [T, m]) = sum_t l(x_t, u_t, t0 + t[, p]) + l_T(x_T[, p])`` from CasADi
expressions, derivatives by CasADi AD, evaluated by one mapped CasADi function (:class:`_RowMap`);
``params`` are passed at call time. The public methods check their input; the solvers validate
the parameters once (:meth:`CasadiCost.check_params`) and call the unchecked kernels ``_total`` /
``_derivatives``. The manual: docs/ilqr.md, "Costs".
"""

from __future__ import annotations

import os
import tempfile
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from mbtsr.validation import as_array, check_int, check_positive

__all__ = [
    "CasadiCost",
    "QuadraticCost",
    "CostDerivatives",
    "casadi_jit_options",
    "quadratic_cost",
    "smooth_norm",
    "truncated_total",
    "after_termination",
]

def casadi_jit_options(opt_level: str = "-O2") -> dict:
    """CasADi ``Function`` options that JIT-compile with the system C compiler (``"shell"``).

    The generated C sources and shared objects go to ``<tmp>/mbtsr-casadi-jit/`` with unique
    names, where CasADi removes them when the function is freed (by default it writes
    ``jit_tmp*.c`` and ``tmp_casadi_compiler_shell*`` files into the current working directory,
    and a killed process leaves them there).
    """
    folder = os.path.join(tempfile.gettempdir(), "mbtsr-casadi-jit")
    os.makedirs(folder, exist_ok=True)
    return {
        "jit": True,
        "compiler": "shell",
        "jit_temp_suffix": True,
        "jit_options": {"flags": [opt_level], "directory": folder + os.sep},
    }


def smooth_norm(v, eps: float):
    """Smooth Euclidean norm ``sqrt(v^T v + eps^2) - eps`` (pseudo-Huber: quadratic near 0,
    linear far away; docs/ilqr.md, "Costs").

    :param v: a CasADi ``SX``/``MX``/``DM`` column or a numpy vector ``[k]``.
    :param eps: smoothing radius > 0.
    :return: a CasADi scalar expression for symbolic input, else a float.
    """
    check_positive("eps", eps)
    if isinstance(v, (ca.SX, ca.MX, ca.DM)):
        return ca.sqrt(ca.dot(v, v) + eps**2) - eps
    v = as_array("v", v, ndim=1)
    return float(np.sqrt(v @ v + eps**2) - eps)


@dataclass(frozen=True)
class CostDerivatives:
    """First and second derivatives of the cost along a trajectory.

    ``lx: [T+1, n]`` (last row: terminal), ``lu: [T, m]``, ``lxx: [T+1, n, n]``,
    ``luu: [T, m, m]``, ``lux: [T, m, n]`` (``d^2 l / du dx``).
    """

    lx: np.ndarray
    lu: np.ndarray
    lxx: np.ndarray
    luu: np.ndarray
    lux: np.ndarray

    def __iter__(self):
        return iter((self.lx, self.lu, self.lxx, self.luu, self.lux))

    def convexified(self) -> CostDerivatives:
        """The same derivatives with every stage Hessian ``[[lxx, lxu], [lux, luu]]`` (and the
        terminal ``lxx``) projected onto the positive semidefinite cone: negative eigenvalues
        set to 0, eigenvectors kept (the nearest PSD matrix in the Frobenius norm). Stages that
        are already PSD are returned bit for bit. Gradients are unchanged.

        Why: docs/ilqr.md, "Costs that are not convex".
        """
        T, m, n = self.lux.shape
        # a constant Hessian (a quadratic cost): decompose stage 0 and the terminal one only
        const = T > 1 and all((a[1:T] == a[0]).all() for a in (self.lxx, self.luu, self.lux))
        s = np.array([0, T]) if const else np.arange(T + 1)
        k = s[:-1]  # the stages with a control (the terminal one, last, has none: zero pad)
        H = np.zeros((s.size, n + m, n + m))
        H[:, :n, :n] = self.lxx[s]
        H[:-1, n:, n:] = self.luu[k]
        H[:-1, n:, :n] = self.lux[k]
        H[:-1, :n, n:] = np.swapaxes(self.lux[k], 1, 2)
        H = 0.5 * (H + np.swapaxes(H, 1, 2))
        w, V = np.linalg.eigh(H)
        bad = w[:, 0] < 0.0  # ascending eigenvalues
        if not bad.any():
            return self
        Hp = (V * np.maximum(w, 0.0)[:, None, :]) @ np.swapaxes(V, 1, 2)
        if const:  # back to every stage
            rows = np.r_[np.zeros(T, dtype=int), 1]
            bad, Hp = bad[rows], Hp[rows]
        lxx, luu, lux = self.lxx.copy(), self.luu.copy(), self.lux.copy()
        lxx[bad] = Hp[bad, :n, :n]
        stages = np.flatnonzero(bad[:T])
        luu[stages] = Hp[stages, n:, n:]
        lux[stages] = Hp[stages, n:, :n]
        return CostDerivatives(self.lx, self.lu, lxx, luu, lux)


_ROWS = 256  # rows per call of a mapped stage function (one compiled shape per cost)


#: JIT-compiled mapped functions by their serialized interpreted form: one compile per process
_COMPILED: dict[str, ca.Function] = {}


class _RowMap:
    """``fn`` (one row: inputs ``[w_i]``) on ``N`` rows, ``rows`` per call of one compiled
    ``fn.map(rows)``, through numpy buffers bound once with ``Function.buffer`` (numpy ``[rows,
    w]`` C order = CasADi ``[w, rows]``; docs/ilqr.md, "Costs").

    :param out_shapes: numpy shape of one row of each output (e.g. ``(m, n)`` for ``lux``).
    :param jit_after: JIT-compile at this call (1: the first; ``None``: never): the same bits
        as CasADi's interpreter; without a C compiler it stays interpreted, with a warning.
    """

    def __init__(self, fn: ca.Function, rows: int, out_shapes: list[tuple[int, ...]],
                 jit_after: int | None) -> None:
        self.mapped, self.rows, self.out_shapes = fn.map(rows), rows, out_shapes
        widths = [fn.size1_in(i) * fn.size2_in(i) for i in range(fn.n_in())]
        self.ins = [np.zeros((rows, w)) for w in widths]
        # zeros: CasADi does not write the structurally zero part of an output
        self.outs = [np.zeros((rows, *s)) for s in out_shapes]
        self.calls, self.jit_after, self.compiled = 0, jit_after, False
        self._bind(False)  # compiled at call ``jit_after`` (__call__), the first included

    def _bind(self, jit: bool) -> None:
        """Build the mapped function (compiled with ``jit``: once per process and function,
        :data:`_COMPILED`) on the buffers."""
        sym = self.mapped.mx_in()
        out = self.mapped.call(sym)
        fn = ca.Function(f"{self.mapped.name()}_rows", sym, out)
        if jit:
            key = fn.serialize()
            try:
                if key not in _COMPILED:
                    _COMPILED[key] = ca.Function(fn.name(), sym, out, casadi_jit_options("-O2"))
                fn = _COMPILED[key]
            except RuntimeError as err:  # no C compiler
                warnings.warn(f"CasADi could not JIT-compile a cost; it stays interpreted: "
                              f"{' '.join(str(err).split())[:300]}", RuntimeWarning, stacklevel=3)
                self.jit_after, jit = None, False
        self.fn, self.compiled = fn, jit
        self.buffer, self.trigger = fn.buffer()
        for i, a in enumerate(self.ins):  # the arrays live as long as self
            self.buffer.set_arg(i, memoryview(a))
        for i, o in enumerate(self.outs):
            self.buffer.set_res(i, memoryview(o))

    def __call__(self, N: int, *args: np.ndarray) -> list[np.ndarray]:
        """``args``: ``[N, w_i]`` or ``[1, w_i]`` (the same row for all) -> ``[N, *out_shape]``."""
        self.calls += 1
        if self.calls == self.jit_after:
            self._bind(True)
        C = self.rows
        if 0 < N <= C:  # one call (the usual case): no chunks
            for buf, a in zip(self.ins, args):
                buf[:N] = a
            self.trigger()
            return [res[:N].copy() for res in self.outs]
        outs = [np.empty((N, *s)) for s in self.out_shapes]
        for s in range(0, N, C):
            r = min(C, N - s)
            for buf, a in zip(self.ins, args):
                buf[:r] = a if a.shape[0] == 1 else a[s:s + r]
            self.trigger()
            for o, res in zip(outs, self.outs):
                o[s:s + r] = res[:r]
        return outs


class CasadiCost:
    """A trajectory cost defined by CasADi functions, with derivatives from CasADi AD.

    ``J = sum_t l(x_t, u_t, t, p_t) + l_T(x_T, p_T)`` (``t`` absolute, ``p_t`` the parameter
    row at time ``t``). Build it from ``casadi.Function`` objects (this constructor) or from
    expressions (:meth:`from_expressions`); its mapped functions are built once, on first use.

    :param stage: ``casadi.Function`` ``(x[n], u[m], t[1]) -> l`` or
        ``(x[n], u[m], t[1], p[p]) -> l`` (scalar output).
    :param terminal: ``casadi.Function`` ``(x[n]) -> l_T`` or ``(x[n], p[p]) -> l_T``.
    :param n: state dimension.
    :param m: input dimension.
    :param params: optional default parameters, ``[p]`` or ``[N_ref, p]`` (used when a call
        gives none). ``p`` is the size of the functions' parameter input.
    :param jit: JIT-compile the mapped stage/terminal functions with the system C compiler
        (CasADi ``"shell"`` compiler; a one-off compile of 0.5-1.5 s, then the same bits 2-5x
        faster): ``True`` at their first call, an integer ``k`` at their ``k``-th (so that short
        runs do not pay the compile), ``False`` never.
    """

    def __init__(
        self,
        stage: ca.Function,
        terminal: ca.Function,
        n: int,
        m: int,
        *,
        params: np.ndarray | None = None,
        jit: bool | int = False,
    ) -> None:
        if not isinstance(stage, ca.Function):
            raise TypeError(f"stage must be a casadi.Function, got {type(stage).__name__}")
        if not isinstance(terminal, ca.Function):
            raise TypeError(f"terminal must be a casadi.Function, got {type(terminal).__name__}")
        n, m = int(n), int(m)
        if n < 1 or m < 1:
            raise ValueError(f"n and m must be >= 1, got n={n}, m={m}")
        p_stage = _check_function("stage", stage, [(n, 1), (m, 1), (1, 1)])
        p_term = _check_function("terminal", terminal, [(n, 1)])
        if p_stage is not None and p_term is not None and p_stage != p_term:
            raise ValueError(
                f"stage and terminal parameter inputs differ in size: {p_stage} and {p_term}"
            )
        p_dim = p_stage if p_stage is not None else (p_term or 0)
        if params is not None and p_stage is None and p_term is None:
            raise ValueError("params given, but neither stage nor terminal takes a parameter input")
        self.n, self.m, self.param_dim = n, m, p_dim
        self.params = None if params is None else self._as_table(params)
        self.jit_after = (1 if jit else None) if isinstance(jit, bool) else check_int("jit", jit, 1)
        # normalised signatures: stage(x, u, t, p), terminal(x, p); SX symbols when the user's
        # functions can be evaluated on SX (fast scalar graphs), MX otherwise
        for sym in (ca.SX, ca.MX):
            x, u = sym.sym("x", n), sym.sym("u", m)
            t, p = sym.sym("t"), sym.sym("p", p_dim)
            try:
                # (p is the optional last argument: as many as each function takes)
                l_expr = stage(*[x, u, t, p][: stage.n_in()])
                lT_expr = terminal(*[x, p][: terminal.n_in()])
                break
            except RuntimeError:
                if sym is ca.MX:
                    raise
        self.stage = ca.Function("stage", [x, u, t, p], [l_expr], ["x", "u", "t", "p"], ["l"])
        self.terminal = ca.Function("terminal", [x, p], [lT_expr], ["x", "p"], ["lT"])
        l, lT = self.stage(x, u, t, p), self.terminal(x, p)
        lx, lu = ca.gradient(l, x), ca.gradient(l, u)
        # outputs are stored transposed where it matters so that the column-major CasADi
        # block [rows, cols] lands in numpy as [..., rows, cols] (see _RowMap)
        self._stage_derivs = ca.Function(
            "stage_derivs",
            [x, u, t, p],
            [
                ca.densify(lx),
                ca.densify(lu),
                ca.densify(ca.jacobian(lx, x)).T,
                ca.densify(ca.jacobian(lu, u)).T,
                ca.densify(ca.jacobian(lu, x)).T,
            ],
        )
        lTx = ca.gradient(lT, x)
        self._terminal_derivs = ca.Function(
            "terminal_derivs", [x, p], [ca.densify(lTx), ca.densify(ca.jacobian(lTx, x)).T]
        )
        self._stage_value = ca.Function("stage_value", [x, u, t, p], [ca.densify(l)])
        self._terminal_value = ca.Function("terminal_value", [x, p], [ca.densify(lT)])
        # the row maps of these four functions, built (and JIT-compiled) on first use
        self._maps: dict[str, tuple[_RowMap, _RowMap]] = {}

    # ------------------------------------------------------------------ construction helpers
    @classmethod
    def from_expressions(
        cls,
        x: ca.SX | ca.MX,
        u: ca.SX | ca.MX,
        stage_expr: ca.SX | ca.MX,
        terminal_expr: ca.SX | ca.MX,
        *,
        t: ca.SX | ca.MX | None = None,
        p: ca.SX | ca.MX | None = None,
        params: np.ndarray | None = None,
        jit: bool | int = False,
    ) -> CasadiCost:
        """Build a cost from symbolic expressions.

        :param x: ``[n, 1]`` state symbol; ``u``: ``[m, 1]`` input symbol.
        :param stage_expr: scalar expression of ``x, u`` (and optionally ``t``, ``p``).
        :param terminal_expr: scalar expression of ``x`` (and optionally ``p``).
        :param t: scalar time symbol used in ``stage_expr`` (absolute time index).
        :param p: ``[p, 1]`` parameter symbol (values are given at call time, or as the
            default ``params``: ``[p]`` or ``[N_ref, p]``).

        An example: docs/ilqr.md, "Costs".
        """
        sym = type(x)
        if not isinstance(x, (ca.SX, ca.MX)) or not isinstance(u, sym):
            raise TypeError("x and u must be CasADi symbols of the same type (SX or MX)")
        if x.shape[1] != 1 or u.shape[1] != 1:
            raise ValueError(f"x and u must be column symbols, got {x.shape} and {u.shape}")
        t = sym.sym("t") if t is None else t
        if p is None and params is not None:
            raise ValueError("params (default parameter values) need p, the parameter symbol")
        extra = [] if p is None else [p]
        stage = ca.Function("stage", [x, u, t, *extra], [stage_expr])
        terminal = ca.Function("terminal", [x, *extra], [terminal_expr])
        return cls(stage, terminal, x.shape[0], u.shape[0], params=params, jit=jit)

    # ------------------------------------------------------------------ parameters
    def check_params(self, params: np.ndarray | None = None) -> np.ndarray:
        """Validate ``params`` (``[p]``, ``[N_ref, p]`` or ``None`` for the defaults) once and
        return the parameter table ``[N_ref, p]`` the private kernels take."""
        if params is None:
            if self.params is not None:
                return self.params
            if self.param_dim:
                raise ValueError(f"params is required: this cost takes a parameter vector of size "
                                 f"{self.param_dim} and has no default")
            return np.zeros((1, 0))
        if not self.param_dim:
            raise ValueError("params given, but this cost takes no parameters")
        return self._as_table(params)

    def _as_table(self, params: object) -> np.ndarray:
        return np.ascontiguousarray(_table("params", params, self.param_dim, "N_ref", ""))

    def params_at(self, t: np.ndarray, params: np.ndarray | None = None) -> np.ndarray:
        """Parameter rows for absolute times ``t: [N]`` -> ``[N, p]`` (last row held)."""
        return _rows(self.check_params(params), np.asarray(t, dtype=np.int64))

    # ------------------------------------------------------------------ evaluation (public)
    def stage_values(
        self, X: np.ndarray, U: np.ndarray, t0: int = 0, params: np.ndarray | None = None
    ) -> np.ndarray:
        """Stage costs ``l(x_t, u_t, t0 + t, p)``.

        :param X: ``[..., T, n]`` states (leading dims are a batch).
        :param U: ``[..., T, m]`` inputs.
        :return: ``[..., T]``.
        """
        X, U = self._check_xu(X, U, len_x_extra=0)
        t0 = check_int("t0", t0, 0)
        return self._batch_values(X, U, np.zeros((0, self.n)), t0, self.check_params(params))[0]

    def terminal_values(
        self, X: np.ndarray, t: int, params: np.ndarray | None = None
    ) -> np.ndarray:
        """Terminal cost ``l_T(x, p)`` at absolute time ``t``: ``X: [..., n]`` -> ``[...]``."""
        X = as_array("X", X)
        if X.ndim < 1 or X.shape[-1] != self.n:
            raise ValueError(f"X must have last dimension n={self.n}, got {list(X.shape)}")
        t = check_int("t", t, 0)
        return self._batch_values(np.zeros((0, self.n)), np.zeros((0, self.m)), X, t,
                                  self.check_params(params))[1]

    def total(
        self, X: np.ndarray, U: np.ndarray, t0: int = 0, params: np.ndarray | None = None
    ) -> float | np.ndarray:
        """Trajectory cost ``J = sum_t l(x_t, u_t, t0+t, p) + l_T(x_T, p)``.

        :param X: ``[..., T+1, n]`` states; ``U``: ``[..., T, m]`` inputs.
        :param params: ``[p]`` or ``[N_ref, p]`` parameters (default: the cost's own).
        :return: a float, or ``[...]`` for batched input.
        """
        X, U = self._check_xu(X, U, len_x_extra=1)
        J = self._total(X, U, check_int("t0", t0, 0), self.check_params(params))
        return float(J) if J.ndim == 0 else J

    def derivatives(
        self, X: np.ndarray, U: np.ndarray, t0: int = 0, params: np.ndarray | None = None
    ) -> CostDerivatives:
        """Cost derivatives along a trajectory (mapped CasADi calls, see :class:`_RowMap`).

        :param X: ``[T+1, n]`` states; ``U``: ``[T, m]`` inputs; ``t0``: time of ``X[0]``.
        :param params: ``[p]`` or ``[N_ref, p]`` parameters (default: the cost's own).
        :return: :class:`CostDerivatives` ``(lx [T+1,n], lu [T,m], lxx [T+1,n,n], luu [T,m,m],
            lux [T,m,n])`` (unpacks as a 5-tuple).
        """
        X, U = self._check_xu(X, U, len_x_extra=1)
        if X.ndim != 2:
            raise ValueError(f"X must be [T+1, n] (no batch), got {list(X.shape)}")
        return self._derivatives(X, U, check_int("t0", t0, 0), self.check_params(params))

    # ------------------------------------------------------------------ kernels (no checks)
    def _total(self, X: np.ndarray, U: np.ndarray, t0: int, table: np.ndarray) -> np.ndarray:
        """:meth:`total` on validated float64 input and a :meth:`check_params` table.
        ``X: [..., T+1, n]``, ``U: [..., T, m]`` -> ``[...]``."""
        ls, lT = self._stage_and_terminal(X, U, t0, table)
        return ls.sum(axis=-1) + lT

    def _stage_and_terminal(
        self, X: np.ndarray, U: np.ndarray, t0: int, table: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Stage costs ``[..., T]`` and terminal costs ``[...]`` of validated trajectories
        ``X: [..., T+1, n]``, ``U: [..., T, m]`` in one CasADi call."""
        return self._batch_values(X[..., :-1, :], U, X[..., -1, :], t0, table)

    def _derivatives(
        self, X: np.ndarray, U: np.ndarray, t0: int, table: np.ndarray
    ) -> CostDerivatives:
        """:meth:`derivatives` on validated float64 input and a :meth:`check_params` table."""
        T = U.shape[0]
        times = np.arange(t0, t0 + T + 1)
        P = table if table.shape[0] == 1 else _rows(table, times)
        stage, terminal = self._row_maps("derivs")
        lx, lu, lxx, luu, lux = stage(T, X[:-1], U, times[:-1, None], P[:-1] if len(P) > 1 else P)
        lxT, lxxT = terminal(1, X[-1:], P[-1:])
        return CostDerivatives(
            lx=np.concatenate([lx, lxT]),
            lu=lu,
            lxx=np.concatenate([lxx, lxxT]),
            luu=luu,
            lux=lux,
        )

    def _row_maps(self, kind: str) -> tuple[_RowMap, _RowMap]:
        """The stage and terminal :class:`_RowMap` of ``kind`` ``"derivs"`` or ``"values"``
        (built, and JIT-compiled with ``jit``, on first use; parameters never rebuild them)."""
        maps = self._maps.get(kind)
        if maps is None:
            n, m = self.n, self.m
            if kind == "derivs":
                shapes = [(n,), (m,), (n, n), (m, m), (m, n)]
                maps = (_RowMap(self._stage_derivs, _ROWS, shapes, self.jit_after),
                        _RowMap(self._terminal_derivs, 1, [(n,), (n, n)], self.jit_after))
            else:
                maps = (_RowMap(self._stage_value, _ROWS, [()], self.jit_after),
                        _RowMap(self._terminal_value, 16, [()], self.jit_after))
            self._maps[kind] = maps
        return maps

    # ------------------------------------------------------------------ internals
    def _check_xu(self, X, U, len_x_extra: int) -> tuple[np.ndarray, np.ndarray]:
        X, U = as_array("X", X), as_array("U", U)
        if X.ndim < 2 or X.shape[-1] != self.n:
            raise ValueError(f"X must be [..., T, n] with n={self.n}, got {list(X.shape)}")
        if U.ndim < 2 or U.shape[-1] != self.m:
            raise ValueError(f"U must be [..., T, m] with m={self.m}, got {list(U.shape)}")
        if X.shape[:-2] != U.shape[:-2] or X.shape[-2] != U.shape[-2] + len_x_extra:
            want = "T+1" if len_x_extra else "T"
            raise ValueError(
                f"X must be [..., {want}, n] for U [..., T, m]: got X {list(X.shape)} and "
                f"U {list(U.shape)}"
            )
        if U.shape[-2] < 1 and len_x_extra == 1:
            raise ValueError("U must hold at least one time step (T >= 1)")
        return X, U

    def _batch_values(self, Xs, Us, XT, t0: int, table) -> tuple[np.ndarray, np.ndarray]:
        """Stage costs ``[..., T]`` of ``Xs [..., T, n], Us [..., T, m]`` at times ``t0 ..
        t0+T-1`` and terminal costs ``[...']`` of ``XT [...', n]`` at ``t0 + T`` (batches
        flattened: one mapped call for each)."""
        batch, T = Us.shape[:-2], Us.shape[-2]
        B = int(np.prod(batch, dtype=np.int64))
        N, ts = B * T, np.tile(np.arange(t0, t0 + T), B)
        XT = np.asarray(XT, dtype=np.float64)
        stage, terminal = self._row_maps("values")
        (ls,) = stage(N, np.asarray(Xs, dtype=np.float64).reshape(N, self.n),
                      np.asarray(Us, dtype=np.float64).reshape(N, self.m), ts[:, None],
                      table if table.shape[0] == 1 else _rows(table, ts))
        XTs = XT.reshape(-1, self.n)
        (lT,) = terminal(XTs.shape[0], XTs, table[min(t0 + T, table.shape[0] - 1)][None])
        return ls.reshape(*batch, T), lT.reshape(XT.shape[:-1])


class QuadraticCost(CasadiCost):
    """Quadratic tracking cost (see :func:`quadratic_cost`); keeps its matrices as attributes
    ``Q, R, Qf [n,n]`` and its default reference ``x_goal [N, n]``, ``u_ref [N, m]``. Its
    parameter row is ``p_t = [x_goal_t, u_ref_t]`` (size ``n + m``): build one for a new
    target with :meth:`reference` and pass it as ``params`` (no recompilation)."""

    Q: np.ndarray
    R: np.ndarray
    Qf: np.ndarray
    x_goal: np.ndarray
    u_ref: np.ndarray

    def reference(self, x_goal: np.ndarray, u_ref: np.ndarray | None = None) -> np.ndarray:
        """The parameter table ``[N, n+m]`` of a goal ``[n]`` / reference ``[N, n]`` and an
        input reference (``None``: zero, ``[m]`` or ``[N', m]``; the shorter is padded with its
        last row)."""
        return _reference_table(x_goal, u_ref, self.n, self.m)


def _table(name: str, value: object, k: int, rows: str, note: str) -> np.ndarray:
    """``value`` as a table ``[N, k]`` with ``N >= 1`` (a vector ``[k]`` is one row)."""
    table = as_array(name, value)
    if table.ndim == 1:
        table = table[None]
    if table.ndim != 2 or table.shape[1] != k or table.shape[0] < 1:
        raise ValueError(f"{name} must be [{k}] or [{rows}, {k}] with {rows} >= 1{note}, got "
                         f"{list(np.shape(value))}")
    return table


def _reference_table(x_goal, u_ref, n: int, m: int) -> np.ndarray:
    xg = _table("x_goal", x_goal, n, "N", " (n from Q)")
    ur = np.zeros((1, m)) if u_ref is None else _table("u_ref", u_ref, m, "N", " (m from R)")
    N = max(xg.shape[0], ur.shape[0])
    return np.hstack([np.concatenate([t, np.repeat(t[-1:], N - t.shape[0], axis=0)])
                      for t in (xg, ur)])


def after_termination(done: np.ndarray) -> np.ndarray:
    """``done [S, T]`` (``done[:, t]``: ``x_{t+1}`` is terminal) -> bool ``[S, T]``, true at
    the steps ``t`` after the first termination (one of ``x_1 .. x_t`` terminal): the steps an
    episode that terminates never reaches."""
    done = np.asarray(done).astype(bool)
    ended_before = np.zeros_like(done)
    ended_before[:, 1:] = np.cumsum(done, axis=1)[:, :-1] > 0
    return ended_before


def terminations(terminated: Callable[[np.ndarray], np.ndarray] | None,
                 X: np.ndarray) -> np.ndarray | None:
    """``done [..., T]`` of trajectories ``X [..., T+1, n]`` (``done[..., t]``: ``x_{t+1}`` is
    terminal) from a termination function ``X [..., n] -> bool [...]`` (``None``: ``None``)."""
    if terminated is None:
        return None
    done = np.asarray(terminated(X[..., 1:, :]), dtype=bool)
    want = X.shape[:-2] + (X.shape[-2] - 1,)
    if done.shape != want:
        raise ValueError(f"terminated(X [..., T, n]) must return bool [..., T] = {list(want)}, "
                         f"got {list(done.shape)}")
    return done


def truncated_total(
    stage: np.ndarray, terminal: np.ndarray, done: np.ndarray, termination_cost: float = 0.0
) -> np.ndarray:
    """Trajectory cost of episodes that end at a termination (PETS's convention).

    Stage ``t`` counts unless one of ``x_1 .. x_t`` is terminal (``x_0`` is the current
    state); a trajectory that terminates pays ``termination_cost`` once instead of the terminal
    cost. ``stage: [S, T]``, ``terminal: [S]``, ``done: [S, T]`` (``done[:, t]``: ``x_{t+1}``
    is terminal) -> ``[S]``.
    """
    stage = np.asarray(stage, dtype=float)
    terminal = np.asarray(terminal, dtype=float)
    done = np.asarray(done)
    if stage.ndim != 2:
        raise ValueError(f"stage must be [S, T] stage costs, got shape {list(stage.shape)}")
    if terminal.shape != stage.shape[:1]:
        raise ValueError(f"terminal must be [S] = {list(stage.shape[:1])} terminal costs, got "
                         f"shape {list(terminal.shape)}")
    if done.shape != stage.shape:
        raise ValueError(f"done (what terminated returns for x_1 .. x_T) must be bool [S, T] = "
                         f"{list(stage.shape)}, got shape {list(done.shape)}")
    done = done.astype(bool)
    J = np.where(after_termination(done), 0.0, stage).sum(axis=1)
    return J + np.where(done.any(axis=1), termination_cost, terminal)


def quadratic_cost(
    Q: np.ndarray,
    R: np.ndarray,
    x_goal: np.ndarray | None = None,
    u_ref: np.ndarray | None = None,
    Qf: np.ndarray | None = None,
    *,
    jit: bool = False,
) -> QuadraticCost:
    """Quadratic tracking cost ``l = (x - x_goal_t)^T Q (x - x_goal_t) + (u - u_ref_t)^T R (u -
    u_ref_t)``, ``l_T`` with ``Qf``, parameters ``p_t = [x_goal_t, u_ref_t]``; no factor 1/2, so
    ``-l`` is the arm env's reward (docs/ilqr.md, "Costs").

    :param Q: ``[n, n]`` symmetric positive semi-definite state weight.
    :param R: ``[m, m]`` symmetric positive semi-definite input weight.
    :param x_goal: default reference: ``[n]`` constant goal or ``[N, n]`` time-indexed
        (row ``t`` at absolute time ``t``; the last row is held after the end); ``None``: zero.
        Other goals are passed at call time: ``params=cost.reference(goal)``.
    :param u_ref: ``None`` (zero), ``[m]`` or ``[N', m]`` default input reference.
    :param Qf: ``[n, n]`` terminal weight; defaults to ``Q``.
    :param jit: JIT-compile the derivative functions (see :class:`CasadiCost`).
    """
    Q = _check_psd("Q", Q)
    n = Q.shape[0]
    R = _check_psd("R", R)
    m = R.shape[0]
    Qf = Q if Qf is None else _check_psd("Qf", Qf)
    if Qf.shape != (n, n):
        raise ValueError(f"Qf must have shape [{n}, {n}] like Q, got {list(Qf.shape)}")
    table = _reference_table(np.zeros(n) if x_goal is None else x_goal, u_ref, n, m)

    x, u, t, p = ca.SX.sym("x", n), ca.SX.sym("u", m), ca.SX.sym("t"), ca.SX.sym("p", n + m)
    ex, eu = x - p[:n], u - p[n:]
    stage = ca.Function(
        "quadratic_stage", [x, u, t, p], [ca.bilin(ca.DM(Q), ex, ex) + ca.bilin(ca.DM(R), eu, eu)]
    )
    terminal = ca.Function("quadratic_terminal", [x, p], [ca.bilin(ca.DM(Qf), ex, ex)])
    cost = QuadraticCost(stage, terminal, n, m, params=table, jit=jit)
    cost.Q, cost.R, cost.Qf = Q, R, Qf
    cost.x_goal, cost.u_ref = table[:, :n].copy(), table[:, n:].copy()
    return cost


# ---------------------------------------------------------------------- helpers
def _check_psd(name: str, M: np.ndarray) -> np.ndarray:
    M = as_array(name, M, ndim=2)
    if M.shape[0] != M.shape[1] or M.shape[0] < 1:
        raise ValueError(f"{name} must be a square [k, k] matrix, got {list(M.shape)}")
    if not np.allclose(M, M.T, rtol=1e-10, atol=1e-12):
        raise ValueError(f"{name} must be symmetric")
    if np.linalg.eigvalsh(M).min() < -1e-10 * max(1.0, np.abs(M).max()):
        raise ValueError(f"{name} must be positive semi-definite")
    return M


def _check_function(name: str, fn: ca.Function, shapes: list[tuple[int, int]]) -> int | None:
    """Check the inputs of ``fn`` (``shapes``, then an optional ``[p, 1]`` parameter input) and
    its scalar output; return ``p`` or ``None`` without a parameter input."""
    k = len(shapes)
    if fn.n_in() not in (k, k + 1):
        raise ValueError(f"{name} must take {k} inputs (or {k + 1} with p), takes {fn.n_in()}")
    for i, s in enumerate(shapes):
        got = fn.size_in(i)
        if tuple(got) != s:
            raise ValueError(f"{name} input {i} must have shape {list(s)}, got {list(got)}")
    if fn.n_out() < 1 or tuple(fn.size_out(0)) != (1, 1):
        raise ValueError(f"{name} must return a scalar as its first output")
    if fn.n_in() == k:
        return None
    rows, cols = fn.size_in(k)
    if cols != 1 and rows * cols != 0:
        raise ValueError(f"{name} parameter input p must be a column [p, 1], got {[rows, cols]}")
    return int(rows * cols)


def _rows(table: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rows ``min(t, N_ref - 1)`` of a parameter table ``[N_ref, p]`` -> ``[len(t), p]``."""
    if table.shape[0] == 1:
        return np.broadcast_to(table[0], (len(t), table.shape[1]))
    return table[np.minimum(t, table.shape[0] - 1)]

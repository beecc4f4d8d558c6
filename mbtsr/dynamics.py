"""The discrete-time dynamics-model protocol at the centre of mbtsr.

Everything that can be planned through (the MuJoCo arm, its analytic twin, an LTV model, a linear
system, a learned ensemble's ``freeze()``) offers ``step(x [..., n], u [..., m], t=None)`` and
``jacobians(x [T, n], u [T, m], t=0) -> (A [T, n, n], B [T, n, m])``; ``_step`` (optional) is
``step`` without input checks. The protocol: docs/architecture.md, "The dynamics protocol".
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol, runtime_checkable

import numpy as np

from mbtsr.validation import as_array, check_int

__all__ = [
    "DynamicsModel",
    "LinearDynamics",
    "check_planning_model",
    "check_step_inputs",
    "check_step_shapes",
    "raw_step",
    "rollout",
]

_F64 = np.dtype(np.float64)  # the fast path's dtype (numpy's built-in dtypes are singletons)


@runtime_checkable
class DynamicsModel(Protocol):
    """A discrete-time model ``x_{t+1} = f(x_t, u_t)`` with batched Jacobians."""

    state_dim: int
    action_dim: int

    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """Next state. ``x: [..., n]``, ``u: [..., m]`` -> ``[..., n]``."""
        ...

    def jacobians(
        self, x: np.ndarray, u: np.ndarray, t: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """``A_t = df/dx``, ``B_t = df/du`` at each row: ``x: [T, n]``, ``u: [T, m]`` ->
        ``([T, n, n], [T, n, m])``."""
        ...


def check_step_inputs(
    x: object, u: object, n: int, m: int, *, finite: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Validate and convert a batched ``(x[..., n], u[..., m])`` pair with matching batch dims
    (float64 arrays of those shapes with a finite sum pass as they are: the fast path)."""
    if (isinstance(x, np.ndarray) and isinstance(u, np.ndarray) and x.dtype is _F64
            and u.dtype is _F64 and x.shape[-1:] == (n,) and u.shape[-1:] == (m,)
            and x.shape[:-1] == u.shape[:-1] and (not finite or math.isfinite(x.sum() + u.sum()))):
        return x, u
    x = as_array("x", x, finite=finite)
    u = as_array("u", u, finite=finite)
    check_step_shapes(x.shape, u.shape, n, m)
    return x, u


def check_step_shapes(x_shape: tuple[int, ...], u_shape: tuple[int, ...], n: int, m: int) -> None:
    """Raise ``ValueError`` unless ``x: [..., n]`` and ``u: [..., m]`` share batch dimensions
    (numpy arrays and torch tensors alike)."""
    x_shape, u_shape = tuple(x_shape), tuple(u_shape)
    if len(x_shape) < 1 or x_shape[-1] != n:
        raise ValueError(f"x must have last dimension n={n}, got shape {list(x_shape)}")
    if len(u_shape) < 1 or u_shape[-1] != m:
        raise ValueError(f"u must have last dimension m={m}, got shape {list(u_shape)}")
    if x_shape[:-1] != u_shape[:-1]:
        raise ValueError(f"x and u must share leading (batch) dimensions, got {list(x_shape)} and "
                         f"{list(u_shape)}")


#: line-search chunk starts where a batch costs its size (simulators, affine models; mbtsr.ilqr)
LINE_SEARCH_CHUNKS = (0, 2, 4, 7)


class LinearDynamics:
    """A time-invariant linear model ``x+ = A x + B u (+ c)``.

    :param A: ``[n, n]`` state matrix.
    :param B: ``[n, m]`` input matrix.
    :param c: optional ``[n]`` affine term."""

    line_search_chunks = LINE_SEARCH_CHUNKS  # iLQR rolls it out in one compiled call per chunk

    def __init__(self, A: np.ndarray, B: np.ndarray, c: np.ndarray | None = None) -> None:
        A = as_array("A", A, ndim=2)
        n = A.shape[0]
        as_array("A", A, (n, n))
        B = as_array("B", B, (n, None))
        self.A, self.B = A, B
        self.c = np.zeros(n) if c is None else as_array("c", c, (n,))
        self.state_dim, self.action_dim = n, B.shape[1]

    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """``A x + B u + c``: ``x: [..., n]``, ``u: [..., m]`` -> ``[..., n]`` (validated)."""
        return self._step(*check_step_inputs(x, u, self.state_dim, self.action_dim), t)

    def _step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        """:meth:`step` without input checks (solver loops)."""
        return x @ self.A.T + u @ self.B.T + self.c

    def jacobians(
        self, x: np.ndarray, u: np.ndarray, t: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        x = as_array("x", x, (None, self.state_dim))
        as_array("u", u, (x.shape[0], self.action_dim))
        T = x.shape[0]
        return (
            np.broadcast_to(self.A, (T, *self.A.shape)).copy(),
            np.broadcast_to(self.B, (T, *self.B.shape)).copy(),
        )


def check_planning_model(model: object, n: int, m: int, name: str = "model") -> Callable:
    """Check once that ``model`` can be planned through with states ``[n]`` and inputs ``[m]``
    (``name``: the argument's name in the messages).

    :return: its step kernel (:func:`raw_step`).
    :raises TypeError: for a trainable model (one with ``freeze``: plan with
        ``model.freeze()``) or an object without ``step``/``jacobians``.
    :raises ValueError: when ``state_dim``/``action_dim`` differ from ``n``/``m``."""
    if hasattr(model, "freeze"):
        raise TypeError(f"model is a trainable {type(model).__name__}: plan with its frozen copy, "
                        "model.freeze() (immutable, numpy, no autograd)")
    if not (callable(getattr(model, "step", None)) and callable(getattr(model, "jacobians", None))):
        raise TypeError(
            f"{name} must have step(x, u, t) and jacobians(x, u, t), got {type(model).__name__}"
        )
    for attr, want in (("state_dim", n), ("action_dim", m)):
        got = getattr(model, attr, want)
        if got != want:
            raise ValueError(f"model.{attr}={got} does not match the cost's dimension {want}")
    return raw_step(model)


def raw_step(model: object) -> Callable:
    """The step kernel of ``model``: ``model._step`` if it has one, else ``model.step``."""
    return getattr(model, "_step", None) or model.step


def rollout(model: DynamicsModel, x0: np.ndarray, u: np.ndarray, t0: int = 0) -> np.ndarray:
    """Simulate ``model`` from ``x0`` driven by ``u``.

    :param x0: ``[..., n]`` initial state(s); leading dims are a batch.
    :param u: ``[T, ..., m]`` inputs (time first), batch dims equal to those of ``x0``.
    :return: ``[T+1, ..., n]`` states. Once a state becomes non-finite, later states stay NaN
        (a diverged simulation is reported, not hidden).

    A trainable model (one with ``freeze``, e.g. a :class:`mbtsr.ensemble.DynamicsEnsemble`)
    is frozen once, in float64 (a metric, not planning), and its frozen copy simulated."""
    if callable(getattr(model, "freeze", None)):
        model = model.freeze("float64")
    x0 = as_array("x0", x0)
    u = as_array("u", u)
    if u.ndim < 2 or x0.ndim < 1 or u.shape[1:-1] != x0.shape[:-1]:
        raise ValueError(
            f"u must be [T, ..., m] with the batch dims of x0 {list(x0.shape[:-1])}, got "
            f"{list(u.shape)}"
        )
    n, m = x0.shape[-1], u.shape[-1]
    for arg, attr, want in (("x0", "state_dim", n), ("u", "action_dim", m)):
        got = getattr(model, attr, want)
        if got != want:
            raise ValueError(f"{arg} has last dimension {want}, but model.{attr}={got}")
    check_int("t0", t0, 0)
    T, batch = u.shape[0], x0.shape[:-1]
    U = np.moveaxis(u.reshape(T, -1, m), 0, 1)  # [B, T, m]
    X, _ = _rollout(model, x0.reshape(-1, n), U, int(t0), np.inf)
    return np.moveaxis(X, 0, 1).reshape(T + 1, *batch, n)


def _rollout(
    model: DynamicsModel, x0: np.ndarray, U: np.ndarray, t0: int, max_norm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Batched open-loop rollout kernel (no input checks).

    ``x0: [n]`` or ``[B, n]``, ``U: [B, T, m]`` -> ``(X [B, T+1, n], alive [B])``. A row whose
    state turns non-finite or exceeds ``max_norm`` in absolute value is dead: its states are NaN
    from then on, and the model is fed ``x0`` in its place (it never sees non-finite input).
    From one ``x0 [n]``, through the model's own batched kernel when it has one and takes the
    batch (:meth:`mbtsr.ensemble.FrozenEnsemble._rollout_open_loop`, the same semantics)."""
    kernel = getattr(model, "_rollout_open_loop", None) if x0.ndim == 1 else None
    out = None if kernel is None else kernel(x0, U, max_norm)
    if out is not None:
        return out
    step = raw_step(model)
    Bsz, T, _ = U.shape
    n = x0.shape[-1]
    X = np.empty((Bsz, T + 1, n))
    X[:, 0] = x0
    x0b = np.broadcast_to(x0, (Bsz, n))
    alive = np.ones(Bsz, dtype=bool)
    x = X[:, 0].copy()
    with np.errstate(all="ignore"):
        for t in range(T):
            xn = np.asarray(step(x, U[:, t], t0 + t), dtype=np.float64).reshape(Bsz, n)
            if not np.abs(xn).max() < max_norm:  # NaN compares false; inf >= max_norm=inf
                bad = ~(np.abs(xn).max(axis=-1) < max_norm)
                alive &= ~bad
            if not alive.all():
                X[:, t + 1] = np.where(alive[:, None], xn, np.nan)
                x = np.where(alive[:, None], xn, x0b)
            else:
                X[:, t + 1] = x = xn
    return X, alive

"""The discrete-time dynamics-model protocol at the centre of mbtsr.

Everything that can be planned through (the MuJoCo arm, its analytic CasADi twin, an LTV model,
a linear system, a learned neural-network ensemble) offers the same small surface, so iLQR,
metrics and experiments never care what is behind it::

    step(x[..., n], u[..., m], t=None) -> x_next[..., n]        # batched over leading dims
    jacobians(x[T, n], u[T, m], t=0) -> (A[T, n, n], B[T, n, m])  # one batched call

``t`` is the time index of the first row. Time-invariant models ignore it; time-varying models
(an LTV model fitted along a trajectory) use it to pick ``A_t, B_t``. For ``step`` a batched call
uses the same ``t`` for every row.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from mbtsr.validation import as_array

__all__ = ["DynamicsModel", "LinearDynamics", "check_step_inputs", "rollout"]


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
    """Validate and convert a batched ``(x[..., n], u[..., m])`` pair with matching batch dims."""
    x = as_array("x", x, finite=finite)
    u = as_array("u", u, finite=finite)
    if x.ndim < 1 or x.shape[-1] != n:
        raise ValueError(f"x must have last dimension n={n}, got shape {list(x.shape)}")
    if u.ndim < 1 or u.shape[-1] != m:
        raise ValueError(f"u must have last dimension m={m}, got shape {list(u.shape)}")
    if x.shape[:-1] != u.shape[:-1]:
        raise ValueError(
            f"x and u must share leading (batch) dimensions, got {list(x.shape)} and "
            f"{list(u.shape)}"
        )
    return x, u


class LinearDynamics:
    """A time-invariant linear model ``x+ = A x + B u (+ c)``.

    :param A: ``[n, n]`` state matrix.
    :param B: ``[n, m]`` input matrix.
    :param c: optional ``[n]`` affine term.
    """

    def __init__(self, A: np.ndarray, B: np.ndarray, c: np.ndarray | None = None) -> None:
        A = as_array("A", A, ndim=2)
        n = A.shape[0]
        as_array("A", A, (n, n))
        B = as_array("B", B, (n, None))
        self.A, self.B = A, B
        self.c = np.zeros(n) if c is None else as_array("c", c, (n,))
        self.state_dim, self.action_dim = n, B.shape[1]

    def step(self, x: np.ndarray, u: np.ndarray, t: int | None = None) -> np.ndarray:
        x, u = check_step_inputs(x, u, self.state_dim, self.action_dim)
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


def rollout(model: DynamicsModel, x0: np.ndarray, u: np.ndarray, t0: int = 0) -> np.ndarray:
    """Simulate ``model`` from ``x0`` driven by ``u``.

    :param x0: ``[..., n]`` initial state(s); leading dims are a batch.
    :param u: ``[T, ..., m]`` inputs (time first).
    :return: ``[T+1, ..., n]`` states. Once a state becomes non-finite, later states stay NaN
        (a diverged simulation is reported, not hidden).
    """
    x0 = as_array("x0", x0)
    u = as_array("u", u)
    if u.ndim < 2:
        raise ValueError(f"u must be [T, ..., m], got shape {list(u.shape)}")
    n = getattr(model, "state_dim", None)
    if n is not None and (x0.ndim < 1 or x0.shape[-1] != n):
        raise ValueError(f"x0 must be [..., n] with n={n}, got shape {list(x0.shape)}")
    out = np.empty((u.shape[0] + 1, *x0.shape))
    out[0] = x0
    for k in range(u.shape[0]):
        if not np.all(np.isfinite(out[k])):
            out[k + 1 :] = np.nan
            break
        with np.errstate(all="ignore"):
            nxt = np.asarray(model.step(out[k], u[k], t0 + k), dtype=float)
        out[k + 1] = np.where(np.isfinite(nxt), nxt, np.nan)
    return out

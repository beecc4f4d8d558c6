"""Trajectory containers: the data every part of mbtsr passes around.

A trajectory of length ``T`` holds ``T + 1`` states and ``T`` inputs, time-major::

    x: [T+1, n]   x[t+1] = f(x[t], u[t])
    u: [T, m]

so ``(x[:-1], u)`` are the regressors and ``x[1:]`` the targets of one-step prediction.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mbtsr.io import atomic_write
from mbtsr.validation import as_array

__all__ = ["Trajectory", "stack_trajectories", "save_trajectories", "load_trajectories"]


@dataclass(frozen=True)
class Trajectory:
    """One rollout ``{x_t, u_t}``.

    :param x: ``[T+1, n]`` states.
    :param u: ``[T, m]`` inputs applied between consecutive states.
    :param dt: sample period in seconds (``None`` if unknown).
    :param meta: free-form metadata (seed, target, env id, ...); kept small and JSON-friendly.
    """

    x: np.ndarray
    u: np.ndarray
    dt: float | None = None
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        x = as_array("x", self.x, ndim=2)
        u = as_array("u", self.u, ndim=2)
        if x.shape[0] != u.shape[0] + 1:
            raise ValueError(
                f"a trajectory needs len(x) == len(u) + 1, got x {list(x.shape)} and "
                f"u {list(u.shape)}"
            )
        if u.shape[0] < 1:
            raise ValueError("a trajectory needs at least one transition (T >= 1)")
        if self.dt is not None and not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"dt must be > 0, got {self.dt!r}")
        x.setflags(write=False)
        u.setflags(write=False)
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "u", u)

    @property
    def T(self) -> int:  # noqa: N802 - the paper's symbol
        """Number of transitions."""
        return self.u.shape[0]

    @property
    def n(self) -> int:
        """State dimension."""
        return self.x.shape[1]

    @property
    def m(self) -> int:
        """Input dimension."""
        return self.u.shape[1]

    @property
    def inputs(self) -> tuple[np.ndarray, np.ndarray]:
        """``(x[:-1], u)``: the regressors of one-step prediction, ``[T, n]`` and ``[T, m]``."""
        return self.x[:-1], self.u

    @property
    def targets(self) -> np.ndarray:
        """``x[1:]``: the one-step targets, ``[T, n]``."""
        return self.x[1:]


def stack_trajectories(trajs: Sequence[Trajectory]) -> tuple[np.ndarray, np.ndarray]:
    """Stack aligned trajectories into ``X [N, T+1, n]`` and ``U [N, T, m]``.

    Raises ``ValueError`` if the trajectories differ in length or dimensions.
    """
    if len(trajs) == 0:
        raise ValueError("trajs must hold at least one Trajectory")
    shapes = {(t.x.shape, t.u.shape) for t in trajs}
    if len(shapes) != 1:
        raise ValueError(f"trajs must share T, n and m to be stacked; got shapes {shapes}")
    return np.stack([t.x for t in trajs]), np.stack([t.u for t in trajs])


def save_trajectories(path: str | os.PathLike, trajs: Iterable[Trajectory]) -> None:
    """Save trajectories to an ``.npz`` file atomically (write to a temporary file, rename).

    Metadata is not stored; only ``x``, ``u`` and ``dt``.
    """
    trajs = list(trajs)
    if not trajs or not all(isinstance(t, Trajectory) for t in trajs):
        raise ValueError("trajs must be a non-empty list of Trajectory")
    path = Path(path)
    arrays: dict[str, np.ndarray] = {"count": np.array(len(trajs))}
    for i, t in enumerate(trajs):
        arrays[f"x{i}"] = t.x
        arrays[f"u{i}"] = t.u
        arrays[f"dt{i}"] = np.array(np.nan if t.dt is None else t.dt)
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:  # a file object: np.savez would append ".npz" to a name
            np.savez(fh, **arrays)

    atomic_write(path, write)


def load_trajectories(path: str | os.PathLike) -> list[Trajectory]:
    """Load trajectories saved by :func:`save_trajectories` (no pickle is ever loaded)."""
    with np.load(path, allow_pickle=False) as z:
        count = int(z["count"])
        out = []
        for i in range(count):
            dt = float(z[f"dt{i}"])
            out.append(Trajectory(z[f"x{i}"], z[f"u{i}"], None if np.isnan(dt) else dt))
    return out

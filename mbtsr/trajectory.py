"""Trajectory containers: the data every part of mbtsr passes around.

A trajectory of length ``T`` holds ``T + 1`` states and ``T`` inputs, time-major::

    x: [T+1, n]   x[t+1] = f(x[t], u[t])
    u: [T, m]

so ``(x[:-1], u)`` are the regressors and ``x[1:]`` the targets of one-step prediction.
"""

from __future__ import annotations

import os
import zipfile
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


def as_trajectory_list(trajs: object, name: str = "trajs",
                       dims: tuple[int, int] | None = None) -> list[Trajectory]:
    """``trajs``, a :class:`Trajectory` or a non-empty sequence (or iterable) of them, as a list;
    otherwise a ``ValueError`` naming ``name`` (and the first entry that is not a Trajectory, or
    whose ``(n, m)`` differs from ``dims``, a model's dimensions)."""
    if isinstance(trajs, Trajectory):
        trajs = [trajs]
    if not isinstance(trajs, Iterable) or isinstance(trajs, (str, bytes, np.ndarray)):
        raise ValueError(f"{name} must be a Trajectory or a non-empty list of Trajectory")
    trajs = list(trajs)
    if not trajs:
        raise ValueError(f"{name} must be a Trajectory or a non-empty list of Trajectory")
    for i, tr in enumerate(trajs):
        if not isinstance(tr, Trajectory):
            raise ValueError(f"{name}[{i}] must be a Trajectory, got {type(tr).__name__}")
        if dims is not None and (tr.n, tr.m) != tuple(dims):
            raise ValueError(f"{name}[{i}] has (n, m) = ({tr.n}, {tr.m}), the model "
                             f"{tuple(dims)}")
    return trajs


def stack_trajectories(
    trajs: Sequence[Trajectory], name: str = "trajs"
) -> tuple[np.ndarray, np.ndarray]:
    """Stack aligned trajectories into ``X [N, T+1, n]`` and ``U [N, T, m]``.

    Raises ``ValueError`` (naming the argument ``name``) if the trajectories differ in length or
    dimensions.
    """
    if len(trajs) == 0:
        raise ValueError(f"{name} must hold at least one Trajectory")
    shapes = {(t.x.shape, t.u.shape) for t in trajs}
    if len(shapes) != 1:
        raise ValueError(f"{name} must share T, n and m to be stacked; got shapes "
                         f"{sorted(shapes)}")
    return np.stack([t.x for t in trajs]), np.stack([t.u for t in trajs])


def save_trajectories(path: str | os.PathLike, trajs: Iterable[Trajectory]) -> None:
    """Save trajectories to an ``.npz`` file atomically (write to a temporary file, rename).

    Metadata is not stored; only ``x``, ``u`` and ``dt``.
    """
    trajs = as_trajectory_list(trajs)
    arrays: dict[str, np.ndarray] = {"count": np.array(len(trajs))}
    for i, t in enumerate(trajs):
        arrays[f"x{i}"] = t.x
        arrays[f"u{i}"] = t.u
        arrays[f"dt{i}"] = np.array(np.nan if t.dt is None else t.dt)
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:  # a file object: np.savez would append ".npz" to a name
            np.savez(fh, **arrays)

    atomic_write(path, write)


def _contents(z: np.lib.npyio.NpzFile) -> dict[str, str]:
    """``{name: "float64 [21, 4]"}`` of every array in an ``.npz`` archive, read from the array
    headers only (nothing is loaded, nothing unpickled)."""
    out = {}
    for name in z.files:
        try:
            with z.zip.open(name + ".npy") as fh:
                read = (np.lib.format.read_array_header_1_0 if np.lib.format.read_magic(fh)
                        == (1, 0) else np.lib.format.read_array_header_2_0)
                shape, _, dtype = read(fh)
            out[name] = f"{'object' if dtype.hasobject else dtype.name} {list(shape)}"
        except (KeyError, ValueError, OSError):
            out[name] = "unreadable"
    return out


def load_trajectories(path: str | os.PathLike) -> list[Trajectory]:
    """Load trajectories saved by :func:`save_trajectories` (no pickle is ever loaded).

    :raises ValueError: naming the file and what it holds: not an ``.npz`` archive, an array of
        Python objects (never unpickled: it could run code), or not the arrays of
        :func:`save_trajectories` (``count``, ``x0``, ``u0``, ``dt0``, ...).
    """
    p = Path(path)
    try:
        z = np.load(p, allow_pickle=False)
    except (FileNotFoundError, IsADirectoryError, PermissionError):
        raise
    except ValueError:  # neither zip nor .npy: numpy would take it for a pickle
        raise ValueError(f"{p} is neither an .npz archive (as save_trajectories writes) nor a "
                         ".npy array; a pickle is never loaded here (it could run code)") from None
    except (OSError, EOFError, zipfile.BadZipFile) as err:
        raise ValueError(f"{p} is not a readable .npz archive of save_trajectories ({err})") \
            from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise ValueError(f"{p} holds a single array {z.dtype.name} {list(z.shape)} (a .npy "
                         "file), not the .npz archive of save_trajectories")
    with z:
        contents = _contents(z)
        held = ", ".join(f"{k}: {v}" for k, v in contents.items()) or "no arrays"

        def get(key: str) -> np.ndarray:
            if contents.get(key, "").startswith("object"):
                raise ValueError(f"{p} holds an array of Python objects, {key!r} ({contents[key]}"
                                 "), which is never unpickled (it could run code): save "
                                 "trajectories with mbtsr.save_trajectories (numeric arrays)")
            if key not in contents:
                objects = any(v.startswith("object") for v in contents.values())
                raise ValueError(f"{p} is not a file of save_trajectories: it has no array "
                                 f"{key!r} and holds {held}" + (
                                     "; arrays of Python objects are never unpickled (they could "
                                     "run code)" if objects else ""))
            return z[key]

        count = get("count")
        if count.shape != () or count.dtype.kind not in "iu" or count < 0:
            raise ValueError(f"{p}: 'count' must be one integer >= 0, got {contents['count']}")
        out = []
        for i in range(int(count)):
            dt = float(get(f"dt{i}"))
            try:
                out.append(Trajectory(get(f"x{i}"), get(f"u{i}"), None if np.isnan(dt) else dt))
            except ValueError as err:
                if str(err).startswith(str(p)):
                    raise
                raise ValueError(f"{p}: trajectory {i}: {err}") from None
    return out

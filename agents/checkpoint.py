"""Crash-safe checkpoint files for the agent.

A checkpoint is ONE file written atomically: the payload goes to a temporary file in the same
directory, is flushed and ``fsync``-ed, then ``os.replace``-d over the old checkpoint and the
directory entry is ``fsync``-ed. A ``SIGKILL`` at any moment therefore leaves either the previous
complete checkpoint or the new complete one, never a torn file.

Everything is loaded without unpickling arbitrary objects: ``torch.load(weights_only=True)``
(tensors, numbers, strings, lists, dicts), ``np.load(allow_pickle=False)`` and JSON.
"""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mbtsr.io import atomic_write_bytes, atomic_write_text

__all__ = [
    "atomic_write_bytes",
    "atomic_write_text",
    "atomic_torch_save",
    "save_checkpoint",
    "load_checkpoint",
    "numpy_rng_state",
    "set_numpy_rng_state",
    "CHECKPOINT_FORMAT",
]

#: bumped when the payload layout changes incompatibly
CHECKPOINT_FORMAT = 1


def atomic_torch_save(obj: Any, path: str | os.PathLike) -> Path:
    """``torch.save`` into memory, then :func:`atomic_write_bytes`."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    return atomic_write_bytes(path, buf.getvalue())


def numpy_rng_state(rng: np.random.Generator) -> str:
    """The full state of a numpy ``Generator`` as a JSON string (``bit_generator.state``)."""
    return json.dumps(rng.bit_generator.state)


def set_numpy_rng_state(rng: np.random.Generator, state: str) -> np.random.Generator:
    """Restore a state produced by :func:`numpy_rng_state` into ``rng`` (in place)."""
    decoded = json.loads(state)
    if decoded.get("bit_generator") != type(rng.bit_generator).__name__:
        raise ValueError(
            f"RNG state is for {decoded.get('bit_generator')!r}, generator uses "
            f"{type(rng.bit_generator).__name__!r}"
        )
    rng.bit_generator.state = decoded
    return rng


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> Path:
    """Atomically save a checkpoint ``payload`` (a dict of tensors, numbers, strings, lists,
    dicts; numpy arrays are converted to tensors) to ``path``."""
    if not isinstance(payload, dict):
        raise TypeError(f"payload must be a dict, got {type(payload).__name__}")
    return atomic_torch_save({"format": CHECKPOINT_FORMAT, **_to_torch(payload)}, path)


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Load a checkpoint written by :func:`save_checkpoint` with ``weights_only=True``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(
            f"{path} is not an agent checkpoint of format {CHECKPOINT_FORMAT} "
            f"(found format {payload.get('format') if isinstance(payload, dict) else None!r})"
        )
    return payload


def _to_torch(obj: Any) -> Any:
    """Recursively turn numpy arrays into tensors so that ``weights_only`` loading works."""
    if isinstance(obj, np.ndarray):
        return torch.from_numpy(np.array(obj, copy=True, order="C"))
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, dict):
        return {k: _to_torch(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_to_torch(v) for v in obj)
    return obj

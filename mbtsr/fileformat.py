"""Checksummed, versioned, atomically written files (checkpoints and saved models): one header
line ``MBTSR1 kind=<kind> version=<int> size=<payload bytes> sha256=<hex>\\n`` then the payload;
reading refuses a truncated, damaged, other-kind or other-version file with a
:class:`CheckpointError` (docs/troubleshooting.md, "Checkpoints and saved models").
"""

from __future__ import annotations

import hashlib
import io
import os
import re
from pathlib import Path
from typing import Any

from mbtsr.io import atomic_write_bytes, remove_stale_temp_files

__all__ = [
    "CheckpointError",
    "read_verified",
    "torch_load_verified",
    "torch_save_verified",
    "write_verified",
]

_MAGIC = b"MBTSR1"
_HEADER_RE = re.compile(
    rb"^MBTSR1 kind=(?P<kind>[A-Za-z0-9_.-]+) version=(?P<version>\d+) size=(?P<size>\d+) "
    rb"sha256=(?P<sha>[0-9a-f]{64})\n"
)
_MAX_HEADER = 256


class CheckpointError(ValueError):
    """A saved file is damaged, of another kind or version, or does not fit what loads it."""


def write_verified(path: str | os.PathLike, payload: bytes, *, kind: str, version: int) -> Path:
    """Atomically write ``payload`` behind a header with its kind, version, size and SHA-256."""
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", kind):
        raise ValueError(f"kind must be letters, digits and _ . -, got {kind!r}")
    header = (
        f"MBTSR1 kind={kind} version={int(version)} size={len(payload)} "
        f"sha256={hashlib.sha256(payload).hexdigest()}\n"
    ).encode()
    remove_stale_temp_files(path)
    return atomic_write_bytes(path, header + payload)


def read_verified(
    path: str | os.PathLike, *, kind: str, versions: tuple[int, ...], what: str = "a saved file"
) -> tuple[bytes, int]:
    """Read a file written by :func:`write_verified` and check it.

    :param kind: the kind the caller expects (a file of another kind is refused).
    :param versions: the format versions the caller reads.
    :param what: what the file should be, with its article, for messages ("an agent
        checkpoint").
    :return: ``(payload, version)``.
    :raises FileNotFoundError: no such file.
    :raises CheckpointError: truncated, damaged (checksum mismatch), another kind or version.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no file at {path} ({what} expected)")
    data = path.read_bytes()
    fix = (f"delete {path} and start again (or restore it from a backup); the file cannot "
           "be used")
    if not data.startswith(_MAGIC):
        if data.startswith(b"PK\x03\x04"):
            raise CheckpointError(
                f"{path} is not {what} with a checksum (a plain torch file: an old format "
                f"or another program's file): pass {what} written by this library")
        raise CheckpointError(f"{path} is not {what} (unknown header): pass the right file")
    m = _HEADER_RE.match(data[:_MAX_HEADER])
    if m is None:
        raise CheckpointError(f"{path}: the header is damaged or truncated: {fix}")
    if m["kind"].decode() != kind:
        raise CheckpointError(
            f"{path} holds a {m['kind'].decode()!r}, not a {kind!r}: pass the right file")
    version = int(m["version"])
    if version not in versions:
        raise CheckpointError(
            f"{path} has format version {version}; this code reads version(s) "
            f"{', '.join(map(str, versions))}: use the matching mbtsr version")
    payload = data[m.end():]
    size = int(m["size"])
    if len(payload) != size:
        raise CheckpointError(
            f"{path} is truncated or padded: {len(payload)} payload bytes, the header says "
            f"{size} (an interrupted copy?): {fix}")
    if hashlib.sha256(payload).hexdigest() != m["sha"].decode():
        raise CheckpointError(
            f"{path} is corrupted: its content does not match the checksum written with it "
            f"(a flipped bit or a damaged copy): {fix}")
    return payload, version


def torch_save_verified(obj: Any, path: str | os.PathLike, *, kind: str, version: int) -> Path:
    """``torch.save`` ``obj`` into memory, then :func:`write_verified`."""
    import torch

    buf = io.BytesIO()
    torch.save(obj, buf)
    return write_verified(path, buf.getvalue(), kind=kind, version=version)


def torch_load_verified(
    path: str | os.PathLike, *, kind: str, versions: tuple[int, ...], what: str = "a saved file"
) -> tuple[Any, int]:
    """:func:`read_verified`, then ``torch.load(weights_only=True)`` (no arbitrary objects).

    :return: ``(object, version)``.
    """
    import pickle

    import torch

    payload, version = read_verified(path, kind=kind, versions=versions, what=what)
    try:
        obj = torch.load(io.BytesIO(payload), map_location="cpu", weights_only=True)
    except (RuntimeError, pickle.UnpicklingError, EOFError, ValueError) as err:
        raise CheckpointError(
            f"{path} passed its checksum but torch.load(weights_only=True) refuses it "
            f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); it was "
            "not written by mbtsr's saver: delete it and start again") from None
    return obj, version

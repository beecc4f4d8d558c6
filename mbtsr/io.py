"""Atomic file writes, the one helper every writer of results, models and media uses: a
temporary file in the target's folder (same suffix), flushed, ``fsync``-ed and ``os.replace``-d
over the target, so a crash leaves the old complete file or the new one, never a torn file.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = [
    "atomic_write",
    "remove_stale_temp_files",
    "temp_path",
    "atomic_write_bytes",
    "atomic_write_text",
    "json_default",
    "write_json_atomic",
]


def _fsync(path: Path, flags: int = os.O_RDONLY) -> None:
    """Persist a file's data or a folder entry on POSIX; a no-op where unsupported."""
    try:
        fd = os.open(path, flags)
    except OSError:  # pragma: no cover - e.g. folders on Windows
        return
    try:
        os.fsync(fd)
    except OSError:  # pragma: no cover
        pass
    finally:
        os.close(fd)


def temp_path(path: Path, pid: int | None = None) -> Path:
    """The temporary file :func:`atomic_write` uses for ``path``: ``.<name>.<pid>.tmp<suffix>``
    in the same folder (same suffix, so format-by-extension writers work)."""
    return path.with_name(f".{path.name}.{os.getpid() if pid is None else pid}.tmp{path.suffix}")


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def remove_stale_temp_files(path: str | os.PathLike) -> list[Path]:
    """Delete temporary files of ``path`` (see :func:`temp_path`) left by a writer that died.

    A temporary file whose writer process is still alive (a concurrent save) is kept.

    :return: the removed files.
    """
    path = Path(path)
    removed: list[Path] = []
    if not path.parent.is_dir():
        return removed
    # also the suffix-less name of earlier versions (``.<name>.<pid>.tmp``)
    pattern = re.compile(
        rf"^\.{re.escape(path.name)}\.(\d+)\.tmp(?:{re.escape(path.suffix)})?$")
    for cand in path.parent.iterdir():
        m = pattern.match(cand.name)
        if m and not _pid_alive(int(m.group(1))):
            try:
                cand.unlink()
                removed.append(cand)
            except OSError:  # pragma: no cover - raced with another cleaner
                pass
    return removed


def atomic_write(path: str | os.PathLike, write: Callable[[Path], Any]) -> Path:
    """Call ``write(tmp_path)`` to write the file, then move it atomically to ``path``.

    :param path: the target; its parent folders are created.
    :param write: writes the complete file at the path it is given (same suffix as ``path``).
    :return: ``path`` as a ``Path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_path(path)
    try:
        write(tmp)
        _fsync(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync(path.parent)
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return atomic_write(path, lambda p: p.write_bytes(data))


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def json_default(o: Any) -> Any:
    """``json.dumps(..., default=json_default)``: numpy values as lists/numbers."""
    if hasattr(o, "tolist"):  # numpy scalars and arrays
        return o.tolist()
    raise TypeError(f"value of type {type(o).__name__} is not JSON-serializable")


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int | None = 1) -> Path:
    """Write ``obj`` as JSON to ``path`` atomically (numpy values become lists/numbers)."""
    return atomic_write_text(path, json.dumps(obj, indent=indent, default=json_default))

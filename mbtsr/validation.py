"""Input checks of the library's public boundary: a bad input fails early with a message
naming the argument and the problem (docs/troubleshooting.md, "Bad arguments").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

__all__ = [
    "as_array",
    "call_user_fn",
    "check_bool",
    "check_callable",
    "check_choice",
    "check_int",
    "check_finite",
    "check_positive",
    "check_nonnegative",
    "check_shape",
    "options_from",
]


def check_finite(name: str, a: np.ndarray) -> np.ndarray:
    """Raise ``ValueError`` if ``a`` holds NaN or inf, naming the first bad index."""
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))
        first = tuple(int(i) for i in bad[0]) if a.ndim else ()
        raise ValueError(
            f"{name} contains {len(bad)} non-finite value(s) (NaN or inf); first at index {first}"
        )
    return a


def check_shape(name: str, a: np.ndarray, shape: Sequence[int | None]) -> np.ndarray:
    """Raise ``ValueError`` unless ``a.shape`` matches ``shape`` (``None`` matches any size)."""
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(a.shape)}")
    return a


def as_array(
    name: str,
    a: object,
    shape: Sequence[int | None] | None = None,
    *,
    ndim: int | None = None,
    dtype: type = np.float64,
    finite: bool = True,
) -> np.ndarray:
    """Convert ``a`` to a numpy array of ``dtype`` and check it.

    :param name: the argument name used in error messages.
    :param shape: expected shape, ``None`` entries match any size.
    :param ndim: expected number of dimensions (alternative to ``shape``).
    :param finite: reject NaN and inf.
    """
    try:
        raw = np.asarray(a)
        complex_to_real = raw.dtype.kind == "c" and np.dtype(dtype).kind != "c"
        arr = None if complex_to_real else np.asarray(raw, dtype=dtype)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{name} must be numeric array-like: {err}") from None
    if arr is None:
        raise ValueError(f"{name} must be real, got complex values (dtype {raw.dtype})")
    if shape is not None:
        check_shape(name, arr, shape)
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must be {ndim}-dimensional, got shape {list(arr.shape)}")
    if finite:
        check_finite(name, arr)
    return arr


def check_int(name: str, value: object, minimum: int | None) -> int:
    """``value`` as an ``int`` if it is an integer (not a bool) ``>= minimum`` (any integer for
    ``minimum=None``), else a ``ValueError`` naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or (
            minimum is not None and value < minimum):
        bound = "" if minimum is None else f" >= {minimum}"
        raise ValueError(f"{name} must be an integer{bound}, got {value!r}")
    return int(value)


def check_choice(name: str, value: Any, choices: Sequence | Mapping) -> Any:
    """``value`` if it is one of ``choices``, else a ``ValueError`` naming ``name`` and them."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
    return value


def check_bool(name: str, value: object) -> bool:
    """``value`` as a ``bool`` if it is one (Python or numpy), else a ``ValueError`` naming
    ``name``."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be a bool, got {value!r}")
    return bool(value)


def check_positive(name: str, value: float) -> float:
    """Raise ``ValueError`` unless ``value`` is a finite number > 0."""
    return _check_number(name, value, ">")


def check_nonnegative(name: str, value: float) -> float:
    """Raise ``ValueError`` unless ``value`` is a finite number >= 0."""
    return _check_number(name, value, ">=")


def _check_number(name: str, value: float, op: str) -> float:
    """``float(value)`` if it is finite and ``op`` (``">"`` or ``">="``) 0, else ``ValueError``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan  # not a number: the same message
    if not np.isfinite(v) or v < 0 or (op == ">" and v == 0):
        raise ValueError(f"{name} must be a finite number {op} 0, got {value!r}")
    return v


def check_callable(name: str, fn: Any, signature: str) -> Callable:
    """Raise ``TypeError`` unless ``fn`` is callable; ``signature`` (e.g. ``"obs -> cost"``)
    says in the message what ``name`` should be."""
    if not callable(fn):
        raise TypeError(f"{name} must be callable {signature}, got {fn!r}")
    return fn


def call_user_fn(fn: Callable, *args: Any, failure: str) -> Any:
    """``fn(*args)`` for a user's function, checked once at the public boundary: any exception
    becomes ONE ``ValueError(f"{failure}: {ExceptionType}: {message}")`` (no traceback chain),
    where ``failure`` names the function and the probe it failed on."""
    try:
        return fn(*args)
    except Exception as err:  # noqa: BLE001 - whatever the user's code raises
        raise ValueError(f"{failure}: {type(err).__name__}: {err}") from None


def options_from(cls: type, options: Any) -> Any:
    """An options dataclass ``cls`` from ``None`` (its defaults), an instance, or a mapping of
    its fields (an unknown field is a ``ValueError`` listing the known ones)."""
    if options is None:
        return cls()
    if isinstance(options, cls):
        return options
    if isinstance(options, Mapping):
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise ValueError(f"unknown {cls.__name__} field(s) {unknown}; known: {sorted(known)}")
        return cls(**options)
    raise TypeError(f"options must be an instance of {cls.__name__}, a dict or None, got "
                    f"{type(options).__name__}")

"""Command lines from config dataclasses (docs/experiments.md). Flags are changes to the
defaults, read as a config file's (:func:`agents.config.replaced`): ``--dotted.field VALUE``,
``--field=VALUE``, a list of values for a tuple, a bool's flag alone for true and ``--no-field``
for false. Every error is one line ``<prog>: error: <message>`` (exit code 2) naming the flag or
field; an unknown flag is named with the closest valid one; fields a config fixes (its
``FIXED``, as :attr:`agents.config.AgentConfig.FIXED`) are not offered."""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import functools
import inspect
import itertools
import os
import re
import shutil
import sys
import textwrap
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from agents.config import closest, describe, hints, leaves, paths, replaced

__all__ = ["call", "check_output_path", "fail", "main", "parse", "usage"]

T = TypeVar("T")
_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|data|mod|attr|obj):`~?([^`]+)`|``([^`]+)``")


def fail(message: str, prog: str | None = None) -> NoReturn:
    """Print ``<prog>: error: <message>`` on stderr and exit with code 2 (argparse's)."""
    print(f"{prog or Path(sys.argv[0]).name}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def check_output_path(path: str | os.PathLike, *, name: str, folder: bool = False) -> Path:
    """``path``, checked that it can be written as a file (a folder with ``folder=True``),
    creating nothing; :raises ValueError: naming ``name`` and the reason."""
    p = Path(path)
    if p.exists() and folder != p.is_dir():
        raise ValueError(f"{name}: {str(p)!r} " + (
            "exists and is not a folder" if folder else "is a folder, expected a file path"))
    target = p if (folder and p.exists()) else p.parent
    while not target.exists():
        target = target.parent
    if not target.is_dir():
        raise ValueError(f"{name}: {str(target)!r} is not a folder, cannot write {str(p)!r}")
    if not os.access(target, os.W_OK | os.X_OK):
        raise ValueError(f"{name}: cannot write in {str(target)!r}")
    return p


def field_docs(cls: type) -> dict[str, str]:
    """``{field: help}`` of a dataclass: its classes' ``:param field:`` entries, the strings
    under the fields and ``metadata["help"]``, with reST markup as plain names."""
    docs: dict[str, str] = {}
    for c in reversed(cls.__mro__[:-1]):
        text = c.__dict__.get("__doc__") or ""
        docs.update(p.split(":", 1) for p in text.split(":param ")[1:])
        with contextlib.suppress(OSError, TypeError, SyntaxError, IndexError):
            body = ast.parse(textwrap.dedent(inspect.getsource(c))).body[0].body
            docs.update((a.target.id, b.value.value) for a, b in zip(body, body[1:]) if isinstance(
                a, ast.AnnAssign) and isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant))
    docs.update((f.name, f.metadata["help"]) for f in dataclasses.fields(cls)
                if "help" in f.metadata)
    return {k: " ".join(_ROLE.sub(lambda m: m.group(1) or m.group(2), v).split())
            for k, v in docs.items()}


def _flat(obj: Any) -> str | None:
    """The field whose flags carry no prefix (``field(metadata={"flat": True})``), if any."""
    return next((f.name for f in dataclasses.fields(obj) if f.metadata.get("flat")), None)


def usage(config: Any, prog: str) -> str:
    """The ``--help`` text: every field a flag with its type, help and default (``config``'s
    value); sections head their groups; the fields a config fixes are left out."""
    width = min(shutil.get_terminal_size().columns, 120) - 6
    out = [f"usage: {prog} [-h] [--FIELD VALUE ...]", "",
           *textwrap.wrap(" ".join((type(config).__doc__ or "").split()), width + 6)]

    def walk(obj: Any, prefix: str, fixed: set[str]) -> None:
        docs, flat = field_docs(type(obj)), _flat(obj)
        fixed = fixed | {prefix + k for k in getattr(obj, "FIXED", ())}
        items = sorted(hints(type(obj)).items(),  # the leaves first, then the sections
                       key=lambda kv: dataclasses.is_dataclass(getattr(obj, kv[0])))
        for name, hint in items:
            value, dotted = getattr(obj, name), prefix + name
            if dataclasses.is_dataclass(value):
                if name != flat:
                    out.extend(["", f"{dotted}: {docs.get(name, '')}"])
                walk(value, "" if name == flat else dotted + ".", fixed)
            elif dotted not in fixed:
                out.append(f"  --{dotted.replace('_', '-')} ({describe(hint)})")
                out.extend(textwrap.wrap(f"{docs.get(name, '')} (default: {value!r})", width,
                                         initial_indent=" " * 6, subsequent_indent=" " * 6))

    walk(config, "", set())
    return "\n".join(out)


def changes(argv: Sequence[str], config: Any, switches: Sequence[str] = ()) -> dict[str, Any]:
    """``{dotted field: value}`` of the flags ``argv`` on ``config``'s fields (``switches``:
    flags that take no value, skipped); :raises ValueError: naming the flag."""
    flat, types, names = _flat(config), {d: h for d, _, h in leaves(config)}, {}
    for p in paths(config):  # flag name -> field; a top-level field wins over the flat one's
        names.setdefault(p.removeprefix(f"{flat}."), p)
    out: dict[str, Any] = {}
    i = 0
    while i < len(argv):
        flag, eq, given = argv[i].partition("=")
        values = [given] if eq else list(itertools.takewhile(
            lambda a: not a.startswith("--"), argv[i + 1:]))
        i += 1 + (0 if eq else len(values))
        name = flag[2:].replace("-", "_")
        head, _, last = name.rpartition(".")
        off = f"{head}.{last[3:]}".lstrip(".")  # --no-x, --a.no-x
        if flag in switches:
            continue
        if not flag.startswith("--"):
            raise ValueError(f"unexpected argument {flag!r} (flags are --field VALUE)")
        if name not in names and last.startswith("no_") and types.get(names.get(off)) is bool:
            name, values = off, values or ["false"]
        if name not in names:
            near = closest(name, names).replace("_", "-")
            raise ValueError(f"unknown flag {flag}; the closest is --{near}")
        if not values and types.get(names[name]) is not bool:
            raise ValueError(f"{flag} needs a value")
        out[names[name]] = values[0] if len(values) == 1 else values or "true"
    return out


def parse(config_type: type[T], *, args: Sequence[str] | None = None, prog: str | None = None,
          outputs: Sequence[str] = (), folders: Sequence[str] = (),
          presets: Mapping[str, Mapping[str, Any]] | None = None, default: T | None = None) -> T:
    """The command line (``args``, default ``sys.argv[1:]``) as a validated ``config_type``;
    ``--help`` exits 0, an error exits 2.

    :param outputs: dotted fields holding output file paths, checked by :func:`check_output_path`
        (``folders``: output folders); ``None``/empty values are skipped.
    :param presets: ``{flag: {field: value}}``: with ``flag`` (``"--smoke"``) given, these values
        are the defaults of the options not given.
    :param default: an instance whose values are the defaults (e.g. a saved run's config).
    """
    prog = prog or Path(sys.argv[0]).name
    argv = list(sys.argv[1:] if args is None else args)
    config = default or config_type()
    for flag, values in (presets or {}).items():
        if flag in argv:
            config = dataclasses.replace(config, **values)
    if {"-h", "--help"} & set(argv):
        print(usage(config, prog))
        raise SystemExit(0)
    flat = _flat(config)
    try:
        given = changes(argv, config, tuple(presets or ()))
        if flat:  # the flat section's errors name its own fields
            given[flat] = replaced(getattr(config, flat), {
                k[len(flat) + 1:]: given.pop(k) for k in list(given) if k.startswith(f"{flat}.")})
        config = replaced(config, given)
        for names, folder in ((outputs, False), (folders, True)):
            for dotted in names:
                value = functools.reduce(getattr, dotted.split("."), config)
                if value not in (None, ""):
                    check_output_path(value, name="--" + dotted.replace("_", "-"), folder=folder)
    except ValueError as err:  # a message that starts with a field names its flag
        msg, m = str(err), re.match(r"[a-z_][\w.]*", str(err))
        if m and m[0] in {p.removeprefix(f"{flat}.") for p in paths(config)}:
            msg = f"--{m[0].replace('_', '-')}{msg[m.end():]}"
        fail(msg, prog)
    return config


def call(run: Callable[[T], Any], config: T) -> Any:
    """``run(config)``, a ``ValueError`` (a bad value) or ``OSError`` (an output the system
    refuses) reported like a bad option (``MBTSR_TRACEBACK=1`` re-raises it)."""
    try:
        return run(config)
    except (ValueError, OSError) as e:
        if os.environ.get("MBTSR_TRACEBACK"):
            raise
        fail(f"{' '.join(str(e).split())} (MBTSR_TRACEBACK=1 shows where)")


def main(config_type: type[T], run: Callable[[T], Any], **options: Any) -> Any:
    """A script's whole body: :func:`call` ``(run, parse(config_type, **options))``."""
    return call(run, parse(config_type, **options))

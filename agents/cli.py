"""Command lines generated from config dataclasses (tyro), with one-line errors.

A script declares its options once, as a dataclass whose field docstrings are the ``--help``
text, and calls :func:`main`. Every bad command line ends in ONE line ``<prog>: error: <message>``
on stderr and exit code 2: tyro's parse errors arrive as events (its ``on_parse_error`` hook, tyro
pinned), and tyro builds the dataclasses unchecked, so :func:`parse` builds them again, innermost
first, naming a bad value by its flag's dotted path. Fields a config fixes (its ``FIXED``, dotted
names, as :attr:`agents.config.AgentConfig.FIXED`) are not offered.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import functools
import io
import os
import re
import sys
import typing
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, NoReturn, TypeVar

__all__ = ["call", "check_output_path", "fail", "main", "parse"]

T = TypeVar("T")
_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|data|mod|attr|obj):`~?([^`]+)`|``([^`]+)``")


def fail(message: str, prog: str | None = None) -> NoReturn:
    """Print ``<prog>: error: <message>`` on stderr and exit with code 2 (argparse's)."""
    print(f"{prog or Path(sys.argv[0]).name}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def _plain_help(text: str) -> str:
    """``--help`` text with the docstrings' reST markup (````x````, :func:`x`) as plain names."""
    return _ROLE.sub(lambda m: m.group(1) or m.group(2), text)


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


def _fields(cls: type) -> Iterator[tuple[dataclasses.Field, str, Any]]:
    """``(field, its flag's name, type)`` of dataclass ``cls`` (``""``: ``arg(name="")``)."""
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        hint, *markers = typing.get_args(hints[f.name]) if typing.get_origin(
            hints[f.name]) is Annotated else (hints[f.name],)
        yield f, "" if any(getattr(m, "name", None) == "" for m in markers) else f.name, hint


def _join(*parts: str) -> str:
    return ".".join(p for p in parts if p)


def _fixed(cls: type) -> set[tuple[type, str]]:
    """``(dataclass, field)`` of every field that a config in ``cls``'s tree fixes."""
    out = set()
    for dotted in getattr(cls, "FIXED", ()):
        *heads, last = dotted.split(".")
        out.add((functools.reduce(lambda c, h: {f.name: t for f, _, t in _fields(c)}[h],
                                  heads, cls), last))
    for _, _, hint in _fields(cls):
        out |= _fixed(hint) if dataclasses.is_dataclass(hint) else set()
    return out


def _flags(cls: type, fixed: set[tuple[type, str]], prefix: str = "") -> list[str]:
    """Every flag of ``cls``'s command line (the suggestions for a misspelt one)."""
    out = []
    for f, name, hint in _fields(cls):
        if dataclasses.is_dataclass(hint):
            out += _flags(hint, fixed, _join(prefix, name))
        elif (cls, f.name) not in fixed:
            out.append("--" + _join(prefix, name).replace("_", "-"))
    return out


def _registry(fixed: set[tuple[type, str]]) -> Any:
    """tyro's dataclass rule, with the ``fixed`` fields suppressed and the values stored
    unchecked (:func:`_validated` builds them)."""
    from tyro.conf import Suppress
    from tyro.constructors import ConstructorRegistry, StructConstructorSpec

    registry, inside = ConstructorRegistry(), []

    def unchecked(cls: type, **values: Any) -> Any:
        obj = object.__new__(cls)
        for k, v in values.items():
            object.__setattr__(obj, k, v)
        return obj

    @registry.struct_rule
    def rule(info: Any) -> Any:
        if inside or not dataclasses.is_dataclass(info.type):
            return None
        inside.append(info)
        try:  # tyro's own rule, from the registries below this one
            spec = ConstructorRegistry.get_struct_spec(info)
        finally:
            inside.pop()
        if not isinstance(spec, StructConstructorSpec):
            return spec
        return dataclasses.replace(spec, instantiate=functools.partial(unchecked, info.type),
                                   fields=tuple(dataclasses.replace(f, type=Annotated[
                                       f.type, Suppress]) if (info.type, f.name) in fixed else f
                                       for f in spec.fields))
    return registry


def _validated(obj: Any, path: str = "") -> Any:
    """``obj`` built again through its constructors, innermost first; an error names the field
    by its flag's dotted path (``model.hidden_width must ...``)."""
    if not dataclasses.is_dataclass(obj):
        return obj
    values = {f.name: _validated(getattr(obj, f.name), _join(path, name))
              for f, name, _ in _fields(type(obj)) if f.init}
    try:
        return type(obj)(**values)
    except (ValueError, TypeError) as err:
        msg = " ".join(str(err).removeprefix("options.").split())  # CEMOptions' options.<field>
        raise ValueError(msg if not path or msg.startswith((f"{path}.", f"{path} "))
                         else f"{path}.{msg}") from None


class _Rejected(Exception):
    """A command line tyro rejected (the message of its parse-error event)."""


def _reject(flags: list[str]) -> Callable[[Any], NoReturn]:
    """The parse-error hook: the event as one message."""
    from tyro import _errors as events

    def hook(event: Any) -> NoReturn:
        arg = getattr(event, "argument", None)
        flag = arg.display_name() if arg is not None else ""
        if isinstance(event, events.UnrecognizedArgs):
            bad = [t for t in event.tokens if t.startswith("-")] or event.tokens
            near = [m for t in bad for m in difflib.get_close_matches(t.split("=")[0], flags, 1)]
            raise _Rejected(f"unrecognized option(s) {' '.join(bad)}" + (
                f"; did you mean {' or '.join(near)}?" if near else ""))
        if isinstance(event, events.InvalidChoice):
            raise _Rejected(f"{flag} must be one of {{{','.join(event.choices)}}}, got "
                            f"{event.value!r}")
        if isinstance(event, events.BadValue):
            raise _Rejected(f"{flag} needs a value" if event.offending_value is None
                            else f"{flag} takes no value, got {event.offending_value!r}")
        if isinstance(event, events.InstantiationFailure):
            raise _Rejected(f"{flag}: {event.message}" if flag else event.message)
        if isinstance(event, events.MissingArgs):
            raise _Rejected("missing " + ", ".join(
                a.arg.display_name() for a in event.missing_arguments))
        raise _Rejected(f"invalid arguments ({type(event).__name__})")
    return hook


def parse(
    config_type: type[T],
    *,
    args: Sequence[str] | None = None,
    description: str | None = None,
    prog: str | None = None,
    outputs: Sequence[str] = (),
    folders: Sequence[str] = (),
    presets: Mapping[str, Mapping[str, Any]] | None = None,
    default: T | None = None,
) -> T:
    """The command line (``args``, default ``sys.argv[1:]``) as a validated ``config_type``;
    ``--help`` exits 0, an error exits 2 after one line.

    :param outputs: dotted fields holding output file paths, checked by :func:`check_output_path`
        (``folders``: output folders); ``None``/empty values are skipped.
    :param presets: ``{flag: {field: value}}``: with ``flag`` (``"--quick"``) given, these values
        are the defaults of the options not given.
    :param default: an instance whose values are the defaults (e.g. a saved run's config).
    """
    import tyro
    from tyro import _errors

    prog = prog or Path(sys.argv[0]).name
    argv = list(sys.argv[1:] if args is None else args)
    for flag, values in (presets or {}).items():
        if flag in argv:
            default = dataclasses.replace(default or config_type(), **values)
    fixed, out = _fixed(config_type), io.StringIO()
    try:
        with _errors.on_parse_error(_reject(_flags(config_type, fixed))), \
                contextlib.redirect_stdout(out):
            config = tyro.cli(config_type, args=argv, description=description, prog=prog,
                              default=default, registry=_registry(fixed))
        config = _validated(config)
    except SystemExit:  # --help
        sys.stdout.write(_plain_help(out.getvalue()))
        raise
    except _Rejected as err:
        fail(f"{err} (see --help)", prog)
    except ValueError as err:
        fail(str(err), prog)
    sys.stdout.write(out.getvalue())
    for names, folder in ((outputs, False), (folders, True)):
        for dotted in names:
            value = functools.reduce(getattr, dotted.split("."), config)
            try:
                if value not in (None, ""):
                    check_output_path(value, name="--" + dotted.replace("_", "-"), folder=folder)
            except ValueError as e:
                fail(str(e), prog)
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


def main(config_type: type[T], run: Callable[[T], Any], *, outputs: Sequence[str] = (),
         folders: Sequence[str] = (), presets: Mapping[str, Mapping[str, Any]] | None = None,
         args: Sequence[str] | None = None) -> Any:
    """A script's whole body: :func:`call` ``(run, parse(config_type, ...))``."""
    return call(run, parse(config_type, args=args, outputs=outputs, folders=folders,
                           presets=presets))

"""Command lines generated from config dataclasses by tyro (docs/experiments.md): a bad value ends
in one line ``<prog>: error: <message>`` (exit code 2) naming the dotted field; fields a config
fixes (its ``FIXED``, as :attr:`agents.config.AgentConfig.FIXED`) are not offered."""

from __future__ import annotations

import dataclasses
import functools
import os
import re
import sys
import typing
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, NoReturn, TypeVar

__all__ = ["built", "call", "check_output_path", "fail", "main", "parse"]

T = TypeVar("T")
_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|data|mod|attr|obj):`~?([^`]+)`|``([^`]+)``")


def fail(message: str, prog: str | None = None) -> NoReturn:
    """Print ``<prog>: error: <message>`` on stderr and exit with code 2 (argparse's)."""
    print(f"{prog or Path(sys.argv[0]).name}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


def _plain_help(text: str | Callable[[], str | None] | None) -> str | None:
    """``--help`` text (or tyro's lazy one) with reST markup (````x````, :func:`x`) as plain."""
    text = text() if callable(text) else text
    return text and _ROLE.sub(lambda m: m.group(1) or m.group(2), text)


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


def _fixed(cls: type) -> set[tuple[type, str]]:
    """``(dataclass, field)`` of every field that a config in ``cls``'s tree fixes."""
    hints = typing.get_type_hints(cls)
    out = {(functools.reduce(lambda c, h: typing.get_type_hints(c)[h], heads, cls), last)
           for *heads, last in (d.split(".") for d in getattr(cls, "FIXED", ()))}
    return out.union(*(_fixed(h) for h in hints.values() if dataclasses.is_dataclass(h)))


def _registry(fixed: set[tuple[type, str]]) -> Any:
    """tyro's dataclass rule with the ``fixed`` fields suppressed, the help texts plain and the
    values stored unchecked (:func:`_validated` builds them)."""
    from tyro.conf import Suppress
    from tyro.constructors import ConstructorRegistry, StructConstructorSpec

    registry, inside = ConstructorRegistry(), []

    def unchecked(cls: type, **values: Any) -> Any:
        obj = object.__new__(cls)
        obj.__dict__.update(values)  # frozen: its __setattr__ refuses
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
                                   fields=tuple(dataclasses.replace(
                                       f, helptext=functools.partial(_plain_help, f.helptext),
                                       type=Annotated[f.type, Suppress]
                                       if (info.type, f.name) in fixed else f.type)
                                       for f in spec.fields))
    return registry


def _validated(obj: Any, path: str = "") -> Any:
    """``obj`` built again through its constructors, innermost first, by :func:`built`."""
    if not dataclasses.is_dataclass(obj):
        return obj
    hints = typing.get_type_hints(type(obj), include_extras=True)
    values = {f.name: _validated(getattr(obj, f.name), path if any(  # tyro.conf.arg(name="")
        getattr(m, "name", None) == "" for m in getattr(hints[f.name], "__metadata__", ()))
        else ".".join(p for p in (path, f.name) if p)) for f in dataclasses.fields(obj) if f.init}
    return built(path, type(obj), **values)


def built(path: str, make: Callable[..., T], *args: Any, **kwargs: Any) -> T:
    """``make(*args, **kwargs)``; its error re-raised as a one-line ``ValueError`` naming the
    dotted field ``path`` (``model.hidden_width must ...``; CEMOptions says ``options.<field>``)."""
    try:
        return make(*args, **kwargs)
    except (ValueError, TypeError) as err:
        msg = " ".join(str(err).removeprefix("options.").split())
        named = not path or msg.startswith((f"{path}.", f"{path} "))
        raise ValueError(msg if named else f"{path}.{msg}") from None


def parse(config_type: type[T], *, args: Sequence[str] | None = None, prog: str | None = None,
          outputs: Sequence[str] = (), folders: Sequence[str] = (),
          presets: Mapping[str, Mapping[str, Any]] | None = None, default: T | None = None) -> T:
    """The command line (``args``, default ``sys.argv[1:]``) as a validated ``config_type``;
    ``--help`` exits 0, an error exits 2.

    :param outputs: dotted fields holding output file paths, checked by :func:`check_output_path`
        (``folders``: output folders); ``None``/empty values are skipped.
    :param presets: ``{flag: {field: value}}``: with ``flag`` (``"--quick"``) given, these values
        (a dict: changes to that section) are the defaults of the options not given.
    :param default: an instance whose values are the defaults (e.g. a saved run's config).
    """
    import tyro

    prog = prog or Path(sys.argv[0]).name
    argv = list(sys.argv[1:] if args is None else args)
    for flag, values in (presets or {}).items():
        if flag in argv:  # a dict for a section: its changes (AgentConfig.replace), on top
            d = default or config_type()
            default = dataclasses.replace(d, **{k: getattr(d, k).replace(v) if isinstance(
                v, Mapping) else v for k, v in values.items()})
    config = tyro.cli(config_type, args=argv, prog=prog, default=default,
                      description=_plain_help(" ".join((config_type.__doc__ or "").split())),
                      registry=_registry(_fixed(config_type)))
    try:
        config = _validated(config)
        for names, folder in ((outputs, False), (folders, True)):
            for dotted in names:
                value = functools.reduce(getattr, dotted.split("."), config)
                if value not in (None, ""):
                    check_output_path(value, name="--" + dotted.replace("_", "-"), folder=folder)
    except ValueError as err:
        fail(str(err), prog)
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

"""Command lines generated from config dataclasses (tyro), with one-line errors.

Every script declares its options once, as a dataclass whose field docstrings are the help text,
and calls :func:`parse`. tyro (rather than argparse builders, click or jsonargparse) because it
reads the dataclasses the library already uses as they are (nested dataclasses become
``--model.hidden-width``-style options, field docstrings become ``--help`` text, ``Literal``
types become choices) and needs no decorators or schema beside them.

On top of tyro, :func:`parse` makes every bad command line end the same way: ONE line
``<prog>: error: <message> (see --help)`` on stderr and exit code 2, never a traceback, also when
the dataclass's own validation (``__post_init__``) rejects a value; and it checks the output
paths named in ``outputs`` (writable, not a folder where a file is expected) before the script
does any work.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import os
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn, TypeVar

__all__ = ["call", "check_output_path", "fail", "main", "parse"]

T = TypeVar("T")
_BOX = re.compile(r"[\u2500-\u257f]")  # rich's box-drawing characters


def fail(message: str, prog: str | None = None) -> NoReturn:
    """Print ``<prog>: error: <message>`` on stderr and exit with code 2 (argparse's)."""
    prog = prog or Path(sys.argv[0]).name
    print(f"{prog}: error: {message}", file=sys.stderr)
    raise SystemExit(2)


# no whitespace inside a mark: --help lays many options out in columns side by side, and a span
# with spaces could pair the marks of two columns
_ROLE = re.compile(r":(?:py:)?(?:func|class|meth|data|mod|attr|obj):`~?([^`\s]+)`|``([^`\s]+)``")


def _plain_help(text: str) -> str:
    """``--help`` text (tyro's plain layout: it is not drawn in boxes when captured) with the
    docstrings' reST markup (``x``, :func:`x`) as plain names."""
    return _ROLE.sub(lambda m: m.group(1) or m.group(2), text)


def _one_line(rich_text: str) -> str:
    """The message of a tyro error box: its first section, box art removed, lines joined.

    tyro draws the box with rich's box characters, or (no unicode terminal) as a title line and
    sections separated by lines of ``-``."""
    title, sections, current = "", [], []
    for line in rich_text.splitlines():
        stripped = line.strip()
        content = _BOX.sub("", stripped).strip()
        if stripped.startswith("\u256d"):  # the title row
            title = content
        elif (not content and "\u2500" in stripped) or re.fullmatch(r"-{3,}", content):
            sections.append(current)  # a separator row
            current = []
        elif content:
            current.append(content)
    sections = [s for s in [*sections, current] if s]
    if not title and len(sections) > 1 and len(sections[0]) == 1:
        title = sections.pop(0)[0]  # the plain title line
    body = sections[0] if sections else []
    message = re.sub(r"\s+", " ", " ".join(body) or title or "invalid arguments")
    flags = _suggested_flags(rich_text)
    return message + (f"; did you mean {' or '.join(flags)}?" if flags else "")


def _suggested_flags(rich_text: str, most: int = 4) -> list[str]:
    """The flags tyro suggests for misspelt ones ("Perhaps you meant:" / "Arguments similar to
    --x:" sections): the least indented ``--flag`` of each entry, ``--no-`` twins left out."""
    flags: list[str] = []
    inside, indent = False, None
    for line in rich_text.splitlines():
        content = _BOX.sub("", line).rstrip()
        if "Perhaps you meant" in content or "Arguments similar to" in content:
            inside, indent = True, None
        elif not content.strip() or re.fullmatch(r"\s*-{3,}", content):
            inside = False
        elif inside and (m := re.match(r"(\s*)(--[\w.-]+)", content)):
            indent = len(m.group(1)) if indent is None else indent
            if len(m.group(1)) == indent and not m.group(2).startswith("--no-") \
                    and m.group(2) not in flags:
                flags.append(m.group(2))
    return flags[:most]


def _qualify(message: str, argv: Sequence[str]) -> str:
    """tyro's ``Error parsing agent.model: hidden_width must ...`` (a nested dataclass rejected a
    value) -> ``model.hidden_width must ...``: the shortest dotted name that is a flag on the
    command line (``--model.hidden-width``); unchanged when none is."""
    m = re.match(r"Error parsing ([\w.]+): ([\w.]+)(.*)$", message)
    if not m:
        return message
    path, name, rest = m.groups()
    name = name.removeprefix("options.")  # mbtsr.cem.CEMOptions names its fields options.<f>
    given = {a.split("=")[0][2:].replace("-", "_") for a in argv if a.startswith("--")}
    parts = path.split(".")
    for i in range(len(parts), -1, -1):
        dotted = ".".join([*parts[i:], name])
        head, _, last = dotted.rpartition(".")
        if dotted in given or f"{head}.no_{last}".lstrip(".") in given:
            return dotted + rest
    return message


def check_output_path(path: str | os.PathLike, *, name: str, folder: bool = False) -> Path:
    """Check that ``path`` can be written (as a file, or a folder with ``folder=True``).

    The nearest existing ancestor must be a writable folder; an existing ``path`` must be of the
    right kind. Nothing is created.

    :raises ValueError: naming ``name`` and the reason.
    """
    p = Path(path)
    if p.exists() and folder and not p.is_dir():
        raise ValueError(f"{name}: {str(p)!r} exists and is not a folder")
    if p.exists() and not folder and p.is_dir():
        raise ValueError(f"{name}: {str(p)!r} is a folder, expected a file path")
    target = p if (folder and p.exists()) else p.parent
    while not target.exists():
        target = target.parent
    if not target.is_dir():
        raise ValueError(f"{name}: {str(target)!r} is not a folder, cannot write {str(p)!r}")
    if not os.access(target, os.W_OK | os.X_OK):
        raise ValueError(f"{name}: cannot write in {str(target)!r}")
    return p


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
    """Parse the command line into ``config_type`` (a dataclass) with tyro.

    :param args: the arguments (default ``sys.argv[1:]``).
    :param presets: ``{flag: {field: value}}``: when ``flag`` (e.g. ``"--quick"``) is on the
        command line, these values replace the defaults, so every option the user does not give
        takes the preset's value (and the ``--help`` shows them).
    :param default: an instance whose values are the defaults (e.g. a saved run's config).
    :param description: the ``--help`` text above the options (default: the class docstring).
    :param outputs: dotted field names holding output FILE paths (``None``/empty values are
        skipped), checked with :func:`check_output_path` before returning.
    :param folders: the same for output FOLDERS.
    :return: the config. ``--help`` prints and exits 0; any error exits 2 after one line.
    """
    import tyro

    prog = prog or Path(sys.argv[0]).name
    argv = list(sys.argv[1:] if args is None else args)
    for flag, values in (presets or {}).items():
        if flag in argv:
            default = dataclasses.replace(default or config_type(), **values)
    err, out = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            config = tyro.cli(config_type, args=argv, description=description, prog=prog,
                              default=default)
    except SystemExit as exit_:
        if exit_.code in (0, None):  # --help
            sys.stdout.write(_plain_help(out.getvalue()))
            sys.stderr.write(err.getvalue())
            raise
        sys.stdout.write(out.getvalue())  # what the config printed while it was parsed
        fail(_qualify(_one_line(err.getvalue()), argv) + " (see --help)", prog)
    except (ValueError, TypeError) as e:  # the dataclass's own validation
        sys.stdout.write(out.getvalue())
        fail(str(e).splitlines()[0] if str(e) else type(e).__name__, prog)
    sys.stdout.write(out.getvalue())
    sys.stderr.write(err.getvalue())  # tyro's warnings, if any
    for names, is_folder in ((outputs, False), (folders, True)):
        for dotted in names:
            value = config
            for part in dotted.split("."):
                value = getattr(value, part)
            if value is None or value == "":  # not given
                continue
            try:
                check_output_path(value, name="--" + dotted.replace("_", "-"), folder=is_folder)
            except ValueError as e:
                fail(str(e), prog)
    return config


def call(run: Callable[[T], Any], config: T) -> Any:
    """``run(config)``, with the ``ValueError`` (or file-system ``OSError``, e.g. an output
    folder that cannot be created) it raises reported like a bad option.

    The library validates its inputs at its public boundary and names the argument in a
    ``ValueError``, so such an error is a bad option value too: one line on stderr, exit code 2
    (``MBTSR_TRACEBACK=1`` re-raises it with the traceback, for debugging). Other exceptions
    (the option types are already checked by the parser, so a ``TypeError`` is a bug) keep
    their traceback.
    """
    try:
        return run(config)
    except (ValueError, OSError) as e:  # a bad value, or an output the system refuses
        if os.environ.get("MBTSR_TRACEBACK"):
            raise
        fail(f"{' '.join(str(e).split())} (MBTSR_TRACEBACK=1 shows where)")


def main(
    config_type: type[T],
    run: Callable[[T], Any],
    *,
    outputs: Sequence[str] = (),
    folders: Sequence[str] = (),
    presets: Mapping[str, Mapping[str, Any]] | None = None,
    args: Sequence[str] | None = None,
) -> Any:
    """A script's whole body: :func:`call` ``(run, parse(config_type, ...))``."""
    config = parse(config_type, args=args, outputs=outputs, folders=folders, presets=presets)
    return call(run, config)

"""Markdown tables for reports: the one helper the benchmarks and experiments write them with."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any

__all__ = ["fmt", "markdown_table"]


def fmt(value: Any, digits: int = 3) -> str:
    """A table cell: ``None``/NaN -> ``-``, floats with ``digits`` significant digits, else str."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return "-" if math.isnan(value) else f"{value:.{digits}g}"
    return str(value)


def markdown_table(
    header: Sequence[str],
    rows: Iterable[Sequence[Any]],
    *,
    align: str | None = None,
    cell: Callable[[Any], str] = fmt,
) -> str:
    """A GitHub markdown table.

    :param header: column titles.
    :param rows: one sequence of values per row (formatted with ``cell``; strings as they are).
    :param align: one character per column, ``l``/``r``/``c`` (default: all left).
    :raises ValueError: a row or ``align`` of another length than ``header``.
    """
    n = len(header)
    align = align or "l" * n
    if len(align) != n or set(align) - set("lrc"):
        raise ValueError(f"align must be {n} characters of l/r/c, got {align!r}")
    rule = {"l": "---", "r": "---:", "c": ":---:"}
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(rule[a] for a in align) + "|"]
    for i, row in enumerate(rows):
        if len(row) != n:
            raise ValueError(f"row {i} has {len(row)} cells, the header {n}")
        lines.append("| " + " | ".join(v if isinstance(v, str) else cell(v) for v in row) + " |")
    return "\n".join(lines)

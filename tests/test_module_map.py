"""docs/architecture.md's module map against the package tree.

Every module of ``mbtsr/``, ``envs/`` and ``agents/`` (a package by its ``__init__.py``) has a row
in the map, and every row names a module that exists. ``agents/experiments/`` may be one row for
the package (then its modules need no rows of their own) or a row per module. When a module is
added, moved or removed, this test names the row to add or delete.
"""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("mbtsr", "envs", "agents")
#: a package that one row of the map may stand for as a whole
SUMMARIZED = "agents.experiments"


def tree_modules(root: Path = REPO) -> set[str]:
    """Dotted names of every module and package under :data:`PACKAGES` (``__init__`` as the
    package itself; ``__pycache__`` and non-Python files ignored)."""
    out = set()
    for pkg in PACKAGES:
        for f in (root / pkg).rglob("*.py"):
            if "__pycache__" in f.parts:
                continue
            parts = list(f.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out.add(".".join(parts))
    return out


def map_modules(markdown: str) -> list[str]:
    """The first-column names of the table in the ``## Module map`` section: the text between
    the first pair of backticks of each row (``| `mbtsr.ltv` | ... |``)."""
    m = re.search(r"^## Module map.*?$(.*?)(?=^## |\Z)", markdown, re.M | re.S)
    if m is None:
        raise AssertionError("docs/architecture.md has no '## Module map' section")
    rows = re.findall(r"^\|\s*`([^`]+)`\s*\|", m.group(1), re.M)
    return rows


def missing_and_stale(tree: set[str], rows: list[str]) -> tuple[list[str], list[str], list[str]]:
    """(modules without a row, rows without a module, rows given twice)."""
    listed = set(rows)
    covered = set(listed)
    if SUMMARIZED in listed:
        covered |= {t for t in tree if t.startswith(SUMMARIZED + ".")}
    missing = sorted(tree - covered)
    stale = sorted(listed - tree)
    twice = sorted({r for r in rows if rows.count(r) > 1})
    return missing, stale, twice


def test_module_map_matches_the_package_tree():
    rows = map_modules((REPO / "docs" / "architecture.md").read_text(encoding="utf-8"))
    missing, stale, twice = missing_and_stale(tree_modules(), rows)
    problems = []
    if missing:
        problems.append(f"modules without a row in docs/architecture.md's module map "
                        f"(add one each): {missing}")
    if stale:
        problems.append(f"rows for modules that do not exist (delete or rename them): {stale}")
    if twice:
        problems.append(f"rows given twice: {twice}")
    assert not problems, "\n".join(problems)


def test_the_check_finds_missing_stale_and_summarized_rows(tmp_path):
    for rel in ("mbtsr/__init__.py", "mbtsr/ltv.py", "mbtsr/_k.py", "envs/__init__.py",
                "agents/__init__.py", "agents/experiments/__init__.py",
                "agents/experiments/bench.py", "agents/__pycache__/x.py", "agents/data.json"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("")
    tree = tree_modules(tmp_path)
    assert tree == {"mbtsr", "mbtsr.ltv", "mbtsr._k", "envs", "agents", "agents.experiments",
                    "agents.experiments.bench"}
    doc = ("# A\n| module | api |\n|---|---|\n| `not.this` | before the section |\n"
           "## Module map (public names)\n\n| module | public API |\n|---|---|\n"
           "| `mbtsr` | x |\n| `mbtsr.ltv` | `fit_ltv` |\n| `mbtsr.gone` | y |\n"
           "| `envs` | z |\n| `agents.experiments` | all |\n| `mbtsr.ltv` | again |\n"
           "## Next\n| `not.this.either` | after |\n")
    rows = map_modules(doc)
    assert rows == ["mbtsr", "mbtsr.ltv", "mbtsr.gone", "envs", "agents.experiments", "mbtsr.ltv"]
    missing, stale, twice = missing_and_stale(tree, rows)
    assert missing == ["agents", "mbtsr._k"]     # agents.experiments.bench: summarized
    assert stale == ["mbtsr.gone"]
    assert twice == ["mbtsr.ltv"]

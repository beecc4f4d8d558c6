"""The documentation's integrity: every stored result is cited, every relative link resolves.

- every file under ``docs/results`` (recursively) is referenced from a doc (``*.md``) or a code
  file, by its path below ``docs/results`` or by a folder that holds it (an experiment's runs
  are cited through their folder); the same for the investigation records in
  ``docs/notes/results``;
- every figure in ``docs/figures`` is embedded as an image in some doc;
- every relative link and image in ``README.md``, ``docs/*.md`` and ``docs/notes/*.md`` points
  to an existing file, and a ``#fragment`` into a markdown file names one of its headings.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
CODE_DIRS = ("agents", "envs", "mbtsr", "scripts", "tests")

#: a markdown link or image: [text](target) / ![alt](target); the target ends at a space or ')'
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)


def manuals() -> list[Path]:
    """The markdown files whose links are checked: README, docs/*.md, docs/notes/*.md."""
    return [REPO / "README.md", *sorted(DOCS.glob("*.md")), *sorted((DOCS / "notes").glob("*.md"))]


def citations(root: str) -> set[str]:
    """Every path named below ``root`` in a doc or code file (docs: all ``*.md``), trailing
    slashes and punctuation stripped: for ``docs/results`` the ``x`` of each ``results/x`` not
    written ``notes/results/x``; for ``docs/notes/results`` the ``x`` of each ``notes/results/x``,
    and of each relative ``results/x`` in a note (``docs/notes/*.md``)."""
    files = [REPO / "README.md", *DOCS.rglob("*.md")]
    for d in CODE_DIRS:
        files += (REPO / d).rglob("*.py")
    tail = r"results/([\w./<>*-]+)"
    anywhere = re.compile(r"(?<!notes/)(?<![\w.-])" + tail)  # docs/results/x, ../results/x
    up = re.compile(r"(?<![\w.-])(?:\.\./|docs/)" + tail)   # from a note: docs/results/x
    notes = re.compile(r"(?<![\w.-])notes/" + tail)
    relative = re.compile(r"(?<!\.\./)(?<!docs/)(?<![\w.-])" + tail)  # a note's own results/x
    out = set()
    for f in files:
        text = f.read_text(encoding="utf-8")
        in_notes = f.parent == DOCS / "notes"
        if root == "docs/results":
            found = (up if in_notes else anywhere).findall(text)
        else:
            found = notes.findall(text) + (relative.findall(text) if in_notes else [])
        out.update(m.rstrip("/.,:;-") for m in found)
    return out


def cited(rel: Path, names: set[str]) -> bool:
    """Whether ``rel`` (a path below the results root) or a folder holding it is in ``names``."""
    return any(p.as_posix() in names for p in (rel, *rel.parents) if str(p) != ".")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    h = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return h.replace(" ", "-")


def anchors(md: Path) -> set[str]:
    """The anchors of a markdown file's headings (outside code fences), duplicates numbered."""
    text = FENCE.sub("", md.read_text(encoding="utf-8"))
    seen: dict[str, int] = {}
    out = set()
    for m in re.finditer(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, re.M):
        s = slug(m.group(1))
        n = seen.get(s, 0)
        out.add(s if n == 0 else f"{s}-{n}")
        seen[s] = n + 1
    return out


def links(md: Path) -> list[str]:
    """The relative link and image targets of a markdown file, outside code fences."""
    text = FENCE.sub("", md.read_text(encoding="utf-8"))
    out = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:
            continue
        out.append(target)
    return out


@pytest.mark.parametrize("root", ["docs/results", "docs/notes/results"])
def test_every_stored_result_is_cited(root):
    base = REPO / root
    names = citations(root)
    missing = [str(p.relative_to(base)) for p in sorted(base.rglob("*"))
               if p.is_file() and not cited(p.relative_to(base), names)]
    assert not missing, (f"{len(missing)} files in {root} that no doc or code file cites (by "
                         f"'results/<path>' or a folder holding them), e.g. {missing[:10]}")


def test_every_figure_is_embedded():
    text = "\n".join(f.read_text(encoding="utf-8") for f in manuals())
    embedded = {Path(t).name for t in re.findall(r"!\[[^\]]*\]\(([^)\s]+)", text)}
    missing = [p.name for p in sorted((DOCS / "figures").glob("*")) if p.name not in embedded]
    assert not missing, f"figures in docs/figures that no doc embeds as an image: {missing}"


def test_relative_links_resolve():
    broken = []
    for md in manuals():
        for target in links(md):
            path, _, fragment = target.partition("#")
            dest = (md.parent / path).resolve() if path else md
            if not dest.exists():
                broken.append(f"{md.relative_to(REPO)}: {target} (no such file)")
            elif fragment and dest.suffix == ".md" and fragment not in anchors(dest):
                broken.append(f"{md.relative_to(REPO)}: {target} (no heading with that anchor)")
    assert not broken, "broken relative links:\n" + "\n".join(broken)


def test_the_checkers_themselves(tmp_path, monkeypatch):
    """The checks themselves: a missing file and a missing anchor are found, a good one is not;
    a result is cited by its path or its folder, and docs/results/x not by notes/results/x."""
    (tmp_path / "b.md").write_text("# A heading, with `code`\n")
    a = tmp_path / "a.md"
    a.write_text("[ok](b.md#a-heading-with-code) [gone](c.md) ![img](d.png) [x](b.md#nope)\n"
                 "```\n[in a fence](e.md)\n```\n[web](https://example.org)\n")
    assert links(a) == ["b.md#a-heading-with-code", "c.md", "d.png", "b.md#nope"]
    assert anchors(tmp_path / "b.md") == {"a-heading-with-code"}
    assert cited(Path("robot/runs/x.json"), {"robot"})
    assert not cited(Path("robot2.json"), {"robot2.json.bak", "robot"})
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    monkeypatch.setattr(sys.modules[__name__], "DOCS", tmp_path / "docs")
    (tmp_path / "README.md").write_text("docs/results/robot/ and docs/notes/results/p.json,\n"
                                        "see results/q.json.")
    (tmp_path / "docs" / "notes").mkdir(parents=True)
    (tmp_path / "docs" / "notes" / "n.md").write_text("[r](results/r.json) [s](../results/s.json)")
    assert citations("docs/results") == {"robot", "q.json", "s.json"}
    assert citations("docs/notes/results") == {"p.json", "r.json"}


def test_readme_states_the_command_ci_runs():
    """CI runs the README's test command verbatim (``.ci/run``): the two must stay equal."""
    ci = [line for line in (REPO / ".ci" / "run").read_text(encoding="utf-8").splitlines()
          if line.startswith("pip install")]
    assert len(ci) == 1, f".ci/run should hold one 'pip install ...' command line, got {ci}"
    readme = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    assert ci[0] in readme, f"README.md no longer contains CI's command line: {ci[0]!r}"

"""Config fields keep short docs: one to three lines (meaning, unit, why this default, with a link), issue 48.

A field of a config dataclass (a ``@dataclass`` class named ``...Config`` anywhere under ``cadalign/``) is documented
by the string literal right under it (STYLE.md, "The stage contract"); measurement logs belong in
``docs/tuning/*.md``, linked from the field. Every config module is parsed with :mod:`ast` (nothing is imported).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import cadalign

PACKAGE_DIR = Path(cadalign.__file__).resolve().parent
MAX_LINES = 3


def _is_dataclass(cls: ast.ClassDef) -> bool:
    for dec in cls.decorator_list:
        target = dec.func if isinstance(dec, ast.Call) else dec
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name == "dataclass":
            return True
    return False


def config_classes(source: str) -> list[ast.ClassDef]:
    """The config dataclasses (``@dataclass`` classes named ``...Config``) of one module's source."""
    tree = ast.parse(source)
    return [n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name.endswith("Config") and _is_dataclass(n)]


def long_field_docs(source: str, max_lines: int = MAX_LINES) -> list[tuple[str, str, int]]:
    """(class, field, lines) of each config field whose docstring, or block of ``#`` comments right above it, spans
    more than ``max_lines`` lines."""
    lines = source.splitlines()
    out = []
    for cls in config_classes(source):
        for i, stmt in enumerate(cls.body):
            if not (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name)):
                continue
            nxt = cls.body[i + 1] if i + 1 < len(cls.body) else None
            n_doc = 0
            if isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant) and isinstance(nxt.value.value, str):
                n_doc = (nxt.end_lineno or nxt.lineno) - nxt.lineno + 1
            n_comment, j = 0, stmt.lineno - 2
            while j >= 0 and lines[j].strip().startswith("#"):
                n_comment, j = n_comment + 1, j - 1
            n = max(n_doc, n_comment)
            if n > max_lines:
                out.append((cls.name, stmt.target.id, n))
    return out


def test_config_field_docs_are_at_most_three_lines() -> None:
    found, n_classes = [], 0
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        source = path.read_text(encoding="utf-8")
        n_classes += len(config_classes(source))
        found += [f"{path.relative_to(PACKAGE_DIR.parent)}: {c}.{f} ({n} lines)" for c, f, n in long_field_docs(source)]
    assert n_classes >= 40, f"only {n_classes} config dataclasses found: is the checker still looking?"
    assert not found, (f"config field docs over {MAX_LINES} lines (keep meaning, unit, why this default and a link; "
                       "move measurements to docs/tuning/*.md):\n" + "\n".join(found))


def test_a_long_field_doc_is_found() -> None:
    source = '''
from dataclasses import dataclass, field
import dataclasses


@dataclass(frozen=True)
class ToyConfig:
    short: int = 1
    """One line."""
    three: float = 0.5
    """Line one,
    two,
    three."""
    long: int = 2
    """Line one,
    two,
    three,
    four: a run log."""
    commented: int = 3
    # one
    # two
    # three
    # four
    after_comments: int = 4
    undocumented: int = 5


@dataclasses.dataclass
class OtherConfig:
    nested: ToyConfig = field(default_factory=ToyConfig)
    """a
    b
    c
    d"""


class NotADataclassConfig:
    x: int = 1
    """a
    b
    c
    d"""


@dataclass
class SomeResult:
    y: int = 1
    """a
    b
    c
    d"""
'''
    assert long_field_docs(source) == [("ToyConfig", "long", 4), ("ToyConfig", "after_comments", 4),
                                       ("OtherConfig", "nested", 4)]
    assert long_field_docs(source, max_lines=4) == []


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation but ``-`` and ``_`` dropped, spaces -> ``-``."""
    kept = "".join(ch for ch in heading.strip().lower() if ch.isalnum() or ch in " -_")
    return kept.replace(" ", "-")


def test_links_to_the_tuning_logs_resolve() -> None:
    """Every ``docs/tuning/NAME.md[#anchor]`` named in the library's source names a file and one of its headings."""
    tuning = PACKAGE_DIR.parent / "docs" / "tuning"
    anchors = {p.name: {_slug(line.lstrip("#")) for line in p.read_text(encoding="utf-8").splitlines()
                        if line.startswith("#")} for p in tuning.glob("*.md")}
    bad, n = [], 0
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        for m in re.finditer(r"docs/tuning/([\w.-]+\.md)(?:#([\w-]+))?", path.read_text(encoding="utf-8")):
            n += 1
            name, anchor = m.groups()
            if name not in anchors or (anchor and anchor not in anchors[name]):
                bad.append(f"{path.relative_to(PACKAGE_DIR.parent)}: {m.group(0)}")
    assert n >= 40
    assert not bad, "links to docs/tuning that do not resolve:\n" + "\n".join(bad)


def test_slug_is_githubs() -> None:
    assert _slug(" RefitConfig.coarse_iters") == "refitconfigcoarse_iters"
    assert _slug(" How the thresholds were chosen (and what they were chosen on)") == (
        "how-the-thresholds-were-chosen-and-what-they-were-chosen-on")

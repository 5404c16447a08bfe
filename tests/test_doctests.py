"""Docstring examples (``>>>``) run as tests: every module of cadalign/geometry, and every other module with one."""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

import cadalign

PACKAGE_DIR = Path(cadalign.__file__).resolve().parent
GEOMETRY_WITH_EXAMPLES = ("camera", "compare", "rotations", "umeyama")
"""cadalign.geometry modules that must keep examples (a test fails if one loses them)."""


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE_DIR.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> list[str]:
    names = []
    for path in sorted(PACKAGE_DIR.rglob("*.py")):
        if path.parent.name == "geometry" or ">>>" in path.read_text(encoding="utf-8"):
            names.append(_module_name(path))
    return names


@pytest.mark.parametrize("name", _modules())
def test_docstring_examples(name: str) -> None:
    if name == "cadalign.geometry.torch_rotations":
        pytest.importorskip("torch")
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, report=False,
                             raise_on_error=False, verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed: python -m doctest -v {name}"
    if name.rpartition(".")[2] in GEOMETRY_WITH_EXAMPLES and name.startswith("cadalign.geometry."):
        assert result.attempted > 0, f"{name} lost its examples"

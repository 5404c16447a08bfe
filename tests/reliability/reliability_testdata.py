"""Helpers shared by the reliability tests (a module, not a conftest, so the name is unique)."""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from typing import Any

import pytest

from cadalign.errors import CadalignError

#: (stage, bad input, exception type or 'WARNING', message) rows, in test order.
CATALOGUE: list[tuple[str, str, str, str]] = []


def expect_error(stage: str, what: str, exc: type[CadalignError], fn: Callable[[], Any], *fragments: str) -> str:
    """Run ``fn``, require ``exc`` whose message holds every fragment; record it in the catalogue."""
    with pytest.raises(exc) as info:
        fn()
    msg = str(info.value)
    for frag in fragments:
        assert frag in msg, f"{frag!r} not in {msg!r}"
    CATALOGUE.append((stage, what, type(info.value).__name__, msg))
    return msg


def expect_warning(stage: str, what: str, caplog: pytest.LogCaptureFixture, fn: Callable[[], Any],
                   *fragments: str) -> Any:
    """Run ``fn`` (it must succeed) and require one WARNING log record holding every fragment."""
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="cadalign"):
        out = fn()
    hits = [r.getMessage() for r in caplog.records
            if r.levelno == logging.WARNING and all(f in r.getMessage() for f in fragments)]
    assert hits, f"no WARNING with {fragments} in {[r.getMessage() for r in caplog.records]}"
    CATALOGUE.append((stage, what, "WARNING (continues)", hits[0]))
    return out


def markdown_table(rows: list[tuple[str, str, str, str]]) -> str:
    """The catalogue as a markdown table (pipes and newlines in messages escaped)."""
    def cell(s: str) -> str:
        s = re.sub(r"/tmp/pytest-of-[^/]+/pytest-[^/]+/[^/]+/", "<tmp>/", s)  # per-run temp folders
        return s.replace("|", "\\|").replace("\n", " ")

    lines = ["| stage | bad input | raises | message the user sees |", "|---|---|---|---|"]
    lines += [f"| {cell(a)} | {cell(b)} | {cell(c)} | {cell(d)} |" for a, b, c, d in rows]
    return "\n".join(lines) + "\n"

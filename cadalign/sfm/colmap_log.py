"""COLMAP's own log (glog, written from C++): quiet by default, counted for the stage's report.

COLMAP prints hundreds of ``I20261129 ... feature_extraction.cc:270] Processed file`` lines. Unless this
package's logger is at DEBUG (``cadalign --log-level debug``) :func:`colmap_log` keeps them off the terminal:
COLMAP's INFO messages are not produced at all, and its warnings and errors go to a temporary glog file
instead of stderr, from which they are counted (:class:`ColmapLog`) for the stage's report. At DEBUG
everything COLMAP says is printed to stderr as COLMAP would.

The switch uses pycolmap's glog flags (``pycolmap.logging``), not a redirection of file descriptor 2, so
rich progress bars and Python logging on stderr keep working while COLMAP runs. A few pycolmap entry points
(``bundle_adjustment``, a bundle adjuster's ``solve``, ``triangulate_points``; pycolmap 4.2) log at INFO whatever
the flags say: wrap those short calls in :func:`stderr_captured`, which redirects file descriptor 2 for the call
and counts what COLMAP wrote into the enclosing :func:`colmap_log` block.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

LINE = re.compile(r"^([IWEF])\d{8} ")
"""A glog line: severity letter, then ``yyyymmdd``."""
EXAMPLES = 3
"""How many distinct warning/error messages a report keeps as examples."""
_ACTIVE: ContextVar[ColmapLog | None] = ContextVar("cadalign_colmap_log", default=None)
"""The innermost open :func:`colmap_log` block (so :func:`stderr_captured` deep in a stage can count into it)."""


@dataclass
class ColmapLog:
    """What COLMAP logged inside one :func:`colmap_log` block (filled when the block ends)."""

    warnings: int = 0
    errors: int = 0
    examples: list[str] = field(default_factory=list)
    """The first few distinct messages (without glog's time/thread prefix)."""
    shown: bool = False
    """True when COLMAP's log went to stderr (debug) and so was not counted."""

    def to_json(self) -> dict[str, Any]:
        return {"warnings": self.warnings, "errors": self.errors, "examples": list(self.examples),
                "shown_not_counted": self.shown}

    def add_text(self, text: str) -> None:
        """Count the W/E/F lines of glog text."""
        for line in text.splitlines():
            m = LINE.match(line)
            if not m or m.group(1) == "I":
                continue
            if m.group(1) == "W":
                self.warnings += 1
            else:
                self.errors += 1
            message = line.split("] ", 1)[-1].strip()
            if len(self.examples) < EXAMPLES and message not in self.examples:
                self.examples.append(message[:300])


def summed(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """One report entry from several :meth:`ColmapLog.to_json` dicts (e.g. one per SfM step)."""
    total = ColmapLog()
    for p in parts:
        total.warnings += int(p.get("warnings", 0))
        total.errors += int(p.get("errors", 0))
        total.shown = total.shown or bool(p.get("shown_not_counted", False))
        for e in p.get("examples", []):
            if len(total.examples) < EXAMPLES and e not in total.examples:
                total.examples.append(e)
    return total.to_json()


def verbose() -> bool:
    """Whether COLMAP's own log is shown: this package's logger is enabled for DEBUG."""
    return logging.getLogger("cadalign").isEnabledFor(logging.DEBUG)


@contextlib.contextmanager
def colmap_log(show: bool | None = None) -> Iterator[ColmapLog]:
    """Run a block of pycolmap calls with COLMAP's log quiet (counted) or shown.

    Args:
        show: print COLMAP's log to stderr; None: :func:`verbose` decides.

    Yields:
        The block's :class:`ColmapLog`; its counts are set when the block ends (also when it raises).
    """
    import pycolmap  # lazy: heavy dependency (pycolmap)

    L = pycolmap.logging
    out = ColmapLog(shown=verbose() if show is None else show)
    token = _ACTIVE.set(out)
    try:
        with _glog_flags(L, out):
            yield out
    finally:
        _ACTIVE.reset(token)


@contextlib.contextmanager
def _glog_flags(L: Any, out: ColmapLog) -> Iterator[None]:
    """Set glog's flags (``L``: ``pycolmap.logging``) for the block, restore them after; count into ``out``."""
    saved = (L.minloglevel, L.alsologtostderr, L.stderrthreshold)
    if out.shown:
        L.minloglevel, L.alsologtostderr, L.stderrthreshold = 0, True, 2
        try:
            yield
        finally:
            L.minloglevel, L.alsologtostderr, L.stderrthreshold = saved
        return
    with tempfile.TemporaryDirectory(prefix="cadalign_colmap_log_") as tmp:
        # every message of WARNING and above goes to the WARNING file; no INFO/ERROR/FATAL files elsewhere
        for level in (L.INFO, L.ERROR, L.FATAL):
            L.set_log_destination(level, "")
        L.set_log_destination(L.WARNING, str(Path(tmp) / "colmap."))
        L.minloglevel, L.alsologtostderr, L.stderrthreshold = 1, False, 3
        try:
            yield
        finally:
            L.set_log_destination(L.WARNING, "")  # closes the file
            L.minloglevel, L.alsologtostderr, L.stderrthreshold = saved
            for f in sorted(Path(tmp).glob("colmap.*")):
                out.add_text(f.read_text(errors="replace"))
            if out.warnings or out.errors:
                log.debug("COLMAP: %d warnings, %d errors (e.g. %s)", out.warnings, out.errors, out.examples[:1])


@contextlib.contextmanager
def stderr_captured() -> Iterator[None]:
    """Inside a quiet :func:`colmap_log` block: send file descriptor 2 to a temporary file for the block and count
    COLMAP's warnings and errors from it; elsewhere (no block, or debug) do nothing. For short pycolmap calls
    without progress bars only: anything else written to stderr meanwhile is logged at DEBUG, not printed."""
    active = _ACTIVE.get()
    if active is None or active.shown:
        yield
        return
    sys.stderr.flush()
    with tempfile.TemporaryFile() as tmp:
        saved = os.dup(2)
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode(errors="replace")
            active.add_text(text)
            if text.strip():
                log.debug("COLMAP (stderr, not shown):\n%s", text.rstrip())

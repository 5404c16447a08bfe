"""Logging, progress bars and error reporting for the CLI (the only place that configures them)."""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Iterable, Iterator, Sized
from typing import TypeVar

import typer
from rich.console import Console
from rich.logging import RichHandler
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from cadalign.errors import CadalignError

T = TypeVar("T")
console = Console(stderr=True)
LOG_LEVELS = ("debug", "info", "warning", "error")


def setup_logging(level: str) -> None:
    """Route library logging through rich at ``level``."""
    logging.basicConfig(
        level=level.upper(),
        format="%(message)s",
        datefmt="[%X]",
        handlers=[RichHandler(console=console, show_path=False, rich_tracebacks=False)],
        force=True,
    )


REFRESH_S = 0.1
"""The progress bar is redrawn at most this often, seconds (and after the last item)."""


def track(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """Iterate with a rich progress bar on stderr.

    The bar is redrawn by the iterating thread as items finish, with no thread of its own (rich's ``track`` starts
    two). A loop left early (an error, Ctrl-C) leaves this generator suspended until the garbage collector closes
    it, in whatever thread runs then: closing a threaded bar there joins its threads, which can wait on a lock that
    thread holds (a test run hung so: a bar's refresh thread closing its own abandoned ``track``)."""
    columns = (
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    if total is None and isinstance(items, Sized):
        total = len(items)
    with Progress(*columns, console=console, transient=False, auto_refresh=False) as progress:
        task = progress.add_task(description, total=total)
        progress.refresh()
        drawn = time.monotonic()
        for item in items:
            yield item
            progress.advance(task)
            if time.monotonic() - drawn >= REFRESH_S:
                progress.refresh()
                drawn = time.monotonic()
        progress.refresh()


@contextlib.contextmanager
def user_errors() -> Iterator[None]:
    """Turn the project's errors into a one-line message and exit code 1 (no traceback); Ctrl-C (SIGINT)
    into a one-line note and exit code 130 (128 + SIGINT, the shell's convention)."""
    try:
        yield
    except CadalignError as exc:
        console.print(f"[bold red]error:[/] {exc}")
        raise typer.Exit(code=1) from None
    except KeyboardInterrupt as exc:  # Ctrl-C has no message; a stage that stops itself may give one
        why = str(exc) or "finished work is kept on disk; re-run the same command to resume"
        console.print(f"[bold yellow]interrupted:[/] {why}")
        raise typer.Exit(code=130) from None

"""Helpers for the real-signal tests: run a ``cadalign`` command as a child process, send it SIGINT (Ctrl-C)
once a condition on disk holds, and compare output trees byte by byte."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

#: the child sees a wide terminal (rich does not wrap the one-line messages) and one thread per library
CHILD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "COLUMNS": "200", "PYTHONUNBUFFERED": "1"}
INTERRUPT_NOTE = "re-run the same command to resume"


@dataclass(frozen=True)
class Stopped:
    """How an interrupted child ended."""

    returncode: int
    stderr: str
    seconds_to_exit: float
    """From the signal to the process's exit."""


def cadalign(*args: str | Path) -> list[str]:
    """The command line of ``cadalign ARGS`` run by this interpreter (the installed entry point's module)."""
    return [sys.executable, "-m", "cadalign.cli.main", *map(str, args)]


def _default_sigint() -> None:
    # a child of a process that ignores SIGINT (nohup, a background job of a script) would inherit SIG_IGN,
    # and Python then installs no KeyboardInterrupt handler: give the child what a terminal user's shell gives
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def run_to_end(cmd: list[str], cwd: Path, timeout: float = 300) -> subprocess.CompletedProcess:
    """Run ``cmd`` to completion; fail loudly (with its stderr) on a non-zero exit."""
    res = subprocess.run(cmd, cwd=cwd, env={**os.environ, **CHILD_ENV}, capture_output=True, text=True,
                         timeout=timeout, preexec_fn=_default_sigint)
    assert res.returncode == 0, f"{' '.join(cmd)} exited {res.returncode}:\n{res.stderr[-3000:]}"
    return res


def interrupt_when(cmd: list[str], cwd: Path, ready: Callable[[], bool], *, timeout: float = 300,
                   poll_s: float = 0.005, sig: int = signal.SIGINT) -> Stopped:
    """Start ``cmd``, wait until ``ready()`` holds, send ``sig`` (``os.kill``; SIGINT = Ctrl-C) and wait for the exit.

    Fails if the command ends before ``ready()`` holds (nothing was interrupted) or does not exit within
    60 s of the signal.
    """
    p = subprocess.Popen(cmd, cwd=cwd, env={**os.environ, **CHILD_ENV}, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)
    t_end = time.monotonic() + timeout
    try:
        while not ready():
            if p.poll() is not None:
                _, err = p.communicate()
                raise AssertionError(f"{' '.join(cmd)} ended (exit {p.returncode}) before the point to interrupt "
                                     f"it:\n{err[-3000:]}")
            if time.monotonic() > t_end:
                raise AssertionError(f"{' '.join(cmd)}: the point to interrupt it was not reached in {timeout} s")
            time.sleep(poll_s)
        t0 = time.monotonic()
        os.kill(p.pid, sig)
        _, err = p.communicate(timeout=60)
        return Stopped(p.returncode, err, time.monotonic() - t0)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def record_interrupt(stage: str, what: str, stopped: Stopped) -> str:
    """Add the user's view of an interrupt (the note's line of stderr, the exit code) to the bad-input catalogue."""
    from reliability_testdata import CATALOGUE

    lines = [" ".join(ln.split()) for ln in stopped.stderr.splitlines() if "interrupted" in ln]
    assert lines, stopped.stderr[-2000:]
    CATALOGUE.append((stage, what, f"exit {stopped.returncode}", lines[-1]))
    return lines[-1]


def tree_digest(root: Path, skip: Callable[[Path], bool] = lambda p: False) -> dict[str, str]:
    """Relative path -> sha256 of every file under ``root`` (``skip(relative path)`` leaves one out)."""
    root = Path(root)
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and not skip(p.relative_to(root))}


def assert_no_torn_files(root: Path) -> int:
    """Every file under ``root`` is whole: no temp files of an atomic write are left, each PNG decodes, each
    JSON parses and each NPZ loads. Returns the number of files checked."""
    import json

    n = 0
    for p in sorted(Path(root).rglob("*")):
        if not p.is_file():
            continue
        n += 1
        assert ".tmp" not in p.name, f"temp file of an interrupted atomic write left behind: {p}"
        if p.suffix == ".png":
            assert cv2.imread(str(p), cv2.IMREAD_UNCHANGED) is not None, f"torn PNG {p}"
        elif p.suffix == ".json":
            json.loads(p.read_text(encoding="utf-8"))
        elif p.suffix == ".npz":
            with np.load(p) as z:
                for k in z.files:
                    z[k]
    return n

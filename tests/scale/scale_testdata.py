"""Helpers of the scale-out tests (a module, not conftest, so imports are unambiguous)."""

from __future__ import annotations

import shutil
from pathlib import Path


def fresh_out(local_build: Path, dst: Path) -> Path:
    """A new OUT holding the reference's sfm/ and align/ (reused by build_dataset when it gets the same
    picks file, ``local_build / "picks.json"``), no dataset/."""
    for name in ("sfm", "align"):
        shutil.copytree(local_build / name, dst / name)
    return dst


def dataset_bytes(out: Path) -> dict[str, bytes]:
    """Every file of OUT/dataset by relative path (temporary files included, so leftovers show up)."""
    ds = out / "dataset"
    return {str(p.relative_to(ds)): p.read_bytes() for p in sorted(ds.rglob("*")) if p.is_file()}


def write_jobs(path: Path, entries: list[dict[str, str]]) -> Path:
    """A jobs file of ``[[video]]`` tables (string values)."""
    path.write_text("".join("[[video]]\n" + "".join(f'{k} = "{v}"\n' for k, v in e.items()) for e in entries))
    return path


def jobs_args(jobs: Path, spec: Path, root: Path, *extra: str) -> list[str]:
    return ["build-dataset", str(jobs), "--cad", str(spec), "--out", str(root), "--preset", "fast", *extra]

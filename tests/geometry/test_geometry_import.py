"""The geometry package must stay numpy/scipy-only at import time."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import cadalign
import cadalign.geometry as geo


def test_import_does_not_pull_torch_or_open3d() -> None:
    code = (
        "import sys, cadalign.geometry; "
        "assert 'torch' not in sys.modules and 'open3d' not in sys.modules, sorted(sys.modules)"
    )
    root = str(Path(cadalign.__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")])}
    subprocess.run([sys.executable, "-c", code], check=True, env=env)


def test_all_names_exist() -> None:
    for name in geo.__all__:
        assert hasattr(geo, name), name

"""Shared fixtures. The real external data lives in ../shared/data beside the repository."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session", autouse=True)
def _one_torch_thread_per_worker() -> None:
    """pytest runs with -n 2 on 2 cores: more torch threads per worker only oversubscribe the CPU
    (measured 8-20x slower network steps on a loaded 2-core machine)."""
    import torch

    torch.set_num_threads(1)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    root = Path(os.environ.get("CADALIGN_DATA_DIR", REPO.parent / "shared" / "data"))
    if not (root / "uuv_subsea_cad").is_dir():
        pytest.fail(
            f"shared test data not found at {root}; set CADALIGN_DATA_DIR to the folder holding uuv_subsea_cad/"
        )
    return root


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO

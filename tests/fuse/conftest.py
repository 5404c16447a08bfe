"""A tiny simulated scene (6 effect-free frames, 160x120) and a small fusion config for the fusion tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from cadalign.fuse.config import FuseConfig
from cadalign.testing.tiny_scene import simulate_tiny


@pytest.fixture(scope="session")
def fuse_sim(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """A `cadalign sim` output folder of the tiny scene (exact depth, class maps, poses, CAD models)."""
    return simulate_tiny(tmp_path_factory.mktemp("fuse_sim"), frames=6)


@pytest.fixture(scope="session")
def small_cfg() -> FuseConfig:
    """3 cm voxels (the tiny scene's pixels are ~3 cm on the structure), a small initial grid."""
    return FuseConfig(voxel_m=0.03, block_count=2000, depth_max_m=12.0)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A RuntimeWarning (NaN, inf, overflow, divide by zero) fails the tests of this folder (issue 11)."""
    here = Path(__file__).parent
    for item in items:
        if here in item.path.parents:
            item.add_marker(pytest.mark.filterwarnings("error::RuntimeWarning"))

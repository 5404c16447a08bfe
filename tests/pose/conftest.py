"""A tiny simulated BOP scene for the detector + pose tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from cadalign.sim.run import SCENE_SUBDIR
from cadalign.testing.tiny_scene import simulate_tiny


@pytest.fixture(scope="session")
def pose_bop(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """The BOP scene folder of a 6-frame effect-free 160x120 simulation (models in ../../models)."""
    return simulate_tiny(tmp_path_factory.mktemp("pose"), frames=6) / SCENE_SUBDIR

"""A tiny simulated BOP scene for the detector + pose tests."""

from __future__ import annotations

from pathlib import Path

import pytest
from sim_testdata import write_tiny_scene


@pytest.fixture(scope="session")
def pose_bop(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """The BOP scene folder of a 6-frame effect-free 160x120 simulation (models in ../../models)."""
    from cadalign.sim.run import SCENE_SUBDIR, simulate

    root = tmp_path_factory.mktemp("pose")
    scene = write_tiny_scene(root / "tiny.toml", effects=[], frames=6)
    return simulate(scene, root / "sim", video=False, contact_sheet=False) / SCENE_SUBDIR

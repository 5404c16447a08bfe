"""A tiny effect-free simulation for the calibration tests (3 frames, 320x240)."""

from __future__ import annotations

from pathlib import Path

import pytest
from sim_testdata import write_tiny_scene


@pytest.fixture(scope="session")
def small_sim(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    from cadalign.sim.run import simulate

    root = tmp_path_factory.mktemp("calib_sim")
    scene = write_tiny_scene(root / "tiny.toml", effects=[], frames=3)
    return simulate(scene, root / "sim", resolution=(320, 240), video=False, contact_sheet=False)

"""A tiny simulated BOP scene for the data-format tests."""

from __future__ import annotations

from pathlib import Path

import pytest
from sim_testdata import write_tiny_scene


@pytest.fixture(scope="session")
def tiny_bop(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """The BOP scene folder of a 3-frame effect-free tiny simulation."""
    from cadalign.sim.run import SCENE_SUBDIR, simulate

    root = tmp_path_factory.mktemp("bop")
    scene = write_tiny_scene(root / "tiny.toml", effects=[], frames=3)
    return simulate(scene, root / "sim", video=False, contact_sheet=False) / SCENE_SUBDIR

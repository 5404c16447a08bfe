"""A tiny simulated BOP scene for the data-format tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from cadalign.sim.run import SCENE_SUBDIR
from cadalign.testing.tiny_scene import simulate_tiny


@pytest.fixture(scope="session")
def tiny_bop(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """The BOP scene folder of a 3-frame effect-free tiny simulation."""
    return simulate_tiny(tmp_path_factory.mktemp("bop"), frames=3) / SCENE_SUBDIR

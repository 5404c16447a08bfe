"""A tiny effect-free simulation for the calibration tests (3 frames, 320x240)."""

from __future__ import annotations

from pathlib import Path

import pytest

from cadalign.testing.tiny_scene import simulate_tiny


@pytest.fixture(scope="session")
def small_sim(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    return simulate_tiny(tmp_path_factory.mktemp("calib_sim"), frames=3, resolution=(320, 240))

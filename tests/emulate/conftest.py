"""Fixtures of the emulation tests: the tiny CAD scene as a layered mesh and a camera pose looking at it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cadalign.testing.tiny_scene import write_tiny_scene
from cadalign.types import Rigid3


@pytest.fixture(scope="session")
def tiny_scene_path(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("emu") / "tiny.toml", effects=[], frames=2)


@pytest.fixture(scope="session")
def tiny_mesh(tiny_scene_path: Path):
    from cadalign.emulate.sources import scene_mesh

    return scene_mesh(tiny_scene_path)


@pytest.fixture(scope="session")
def tiny_cam_pose() -> Rigid3:
    from cadalign.sim.trajectory import look_at

    return look_at(np.array([3.0, -2.0, 1.6]), np.array([0.0, 0.0, 0.4]))


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A RuntimeWarning (NaN, inf, overflow, divide by zero) fails the tests of this folder (issue 11)."""
    here = Path(__file__).parent
    for item in items:
        if here in item.path.parents:
            item.add_marker(pytest.mark.filterwarnings("error::RuntimeWarning"))

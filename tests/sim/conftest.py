"""Tiny simulated scenes shared by the simulator tests (seeded, 160x120, a handful of frames)."""

from __future__ import annotations

from pathlib import Path

import pytest

from cadalign.sim.run import simulate
from cadalign.testing.tiny_scene import ALL_EFFECTS, write_tiny_scene


@pytest.fixture(scope="session")
def tiny_scene_file(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("scene") / "tiny.toml", effects=ALL_EFFECTS)


@pytest.fixture(scope="session")
def tiny_sim(tmp_path_factory: pytest.TempPathFactory, tiny_scene_file: Path) -> Path:
    """A finished simulation of the tiny scene with every effect on."""
    return simulate(tiny_scene_file, tmp_path_factory.mktemp("sim") / "out")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A RuntimeWarning (NaN, inf, overflow, divide by zero) fails the tests of this folder (issue 11)."""
    here = Path(__file__).parent
    for item in items:
        if here in item.path.parents:
            item.add_marker(pytest.mark.filterwarnings("error::RuntimeWarning"))

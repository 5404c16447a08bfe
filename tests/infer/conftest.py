"""A tiny simulated scene (4 frames, exact BOP truth, video) shared by the inference tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from cadalign.sim.structure import load_structure
from cadalign.testing.tiny_scene import simulate_tiny


@pytest.fixture(scope="session")
def tiny_sim(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """``cadalign sim`` output of the tiny scene, effect free; the scene TOML is ``tiny_sim.parent / "tiny.toml"``."""
    return simulate_tiny(tmp_path_factory.mktemp("infer_sim"), frames=4, video=True)


@pytest.fixture(scope="session")
def tiny_structure(tiny_sim: Path):
    return load_structure(tiny_sim.parent / "tiny.toml")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A RuntimeWarning (NaN, inf, overflow, divide by zero) fails the tests of this folder (issue 11)."""
    here = Path(__file__).parent
    for item in items:
        if here in item.path.parents:
            item.add_marker(pytest.mark.filterwarnings("error::RuntimeWarning"))

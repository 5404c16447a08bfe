"""A tiny simulated scene (4 frames, exact BOP truth, video) shared by the inference tests."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))

from sim_testdata import write_tiny_scene  # noqa: E402


@pytest.fixture(scope="session")
def tiny_sim(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """``cadalign sim`` output of the tiny scene, effect free; the scene TOML is ``tiny_sim.parent / "tiny.toml"``."""
    from cadalign.sim.run import simulate

    root = tmp_path_factory.mktemp("infer_sim")
    scene = write_tiny_scene(root / "tiny.toml", effects=[], frames=4)
    return simulate(scene, root / "sim", video=True, contact_sheet=False)


@pytest.fixture(scope="session")
def tiny_structure(tiny_sim: Path):
    from cadalign.build_dataset import load_structure

    return load_structure(tiny_sim.parent / "tiny.toml")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A RuntimeWarning (NaN, inf, overflow, divide by zero) fails the tests of this folder (issue 11)."""
    here = Path(__file__).parent
    for item in items:
        if here in item.path.parents:
            item.add_marker(pytest.mark.filterwarnings("error::RuntimeWarning"))

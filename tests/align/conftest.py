"""Fixtures for the alignment tests: the synthetic structure, its surface samples and SfM-like clouds."""

from __future__ import annotations

from pathlib import Path

import pytest
from align_testdata import SyntheticCloud, make_cloud, structure_parts

from cadalign.align import PRESETS, AlignResult, CadSurface, align, sample_surface
from cadalign.cad import CadModel
from cadalign.types import Rigid3


@pytest.fixture(scope="session")
def parts() -> list[tuple[CadModel, Rigid3]]:
    """The frame and four valves, posed in the world (metres)."""
    return structure_parts()


@pytest.fixture(scope="session")
def surface(parts) -> CadSurface:
    """Surface samples of the structure, as the fast preset takes them."""
    return sample_surface(parts, PRESETS["fast"].cad_samples, 0)


@pytest.fixture(scope="session")
def cloud() -> SyntheticCloud:
    """The reference case: 45 % seabed, 3 % gross outliers, 1.5 cm noise, a random Sim3 (seed 3)."""
    return make_cloud(3)


@pytest.fixture(scope="session")
def small_cloud() -> SyntheticCloud:
    """A lighter cloud (2000 structure points) for the many ICP-only tests."""
    return make_cloud(11, n_structure=2000)


@pytest.fixture(scope="session")
def global_result(cloud, surface) -> AlignResult:
    """Global registration + ICP of the reference case with the fast preset (shared: it takes seconds)."""
    return align(cloud.points_sfm, surface, PRESETS["fast"])


@pytest.fixture(scope="session")
def default_scene(shared_data):
    """The default simulator scene's 17 objects as posed CAD parts, and a cloud of it on its real seabed
    in an SfM frame 20 units per metre (one extreme of the scale range)."""
    import numpy as np
    from align_testdata import default_scene_parts, make_scene_cloud

    from cadalign.geometry import random_rotation
    from cadalign.types import Sim3

    rng = np.random.default_rng(20)
    scene_parts, seabed = default_scene_parts()
    sfm_from_cad = Sim3(20.0, random_rotation(rng), rng.uniform(-100, 100, 3))
    return scene_parts, make_scene_cloud(0, scene_parts, seabed, sfm_from_cad=sfm_from_cad)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """A RuntimeWarning (NaN, inf, overflow, divide by zero) fails the tests of this folder (issue 11)."""
    here = Path(__file__).parent
    for item in items:
        if here in item.path.parents:
            item.add_marker(pytest.mark.filterwarnings("error::RuntimeWarning"))

"""A tiny capture built once with the local executor: the reference the Ray builds must reproduce byte for byte.

The scene and picks are those of tests/build/test_build_dataset.py (a 12-frame 320x240 orbit round a 2 m
block; picks with 2 cm noise make the alignment fast and independent of the global registration).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cadalign.build.run import build_dataset
from cadalign.sfm import PRESETS, run
from cadalign.sim.run import simulate
from cadalign.testing.tiny_scene import write_build_capture, write_picks_from_truth


@pytest.fixture(scope="session")
def scale_capture(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> tuple[Path, Path]:
    """(scene spec, simulator output) of a 12-frame 320x240 orbit, no water effects."""
    root = tmp_path_factory.mktemp("scale_capture")
    spec = write_build_capture(root / "tiny.toml", effects=[], frames=12)
    return spec, simulate(spec, root / "sim", video=False, contact_sheet=False)


@pytest.fixture(scope="session")
def local_build(scale_capture: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """OUT of ``build_dataset(..., executor=None)`` (sfm/, align/, dataset/, picks.json)."""
    spec, sim = scale_capture
    out = tmp_path_factory.mktemp("local_build")
    sfm_dir = run(PRESETS["fast"], sim / "frames", out / "sfm")
    write_picks_from_truth(sfm_dir, sim, out / "picks.json")
    return build_dataset(sim / "frames", spec, out, preset="fast", picks=out / "picks.json")


@pytest.fixture(scope="session")
def ddp_scene(local_build: Path) -> Path:
    """The dataset the DDP tests train on: the reference build (12 frames, 320x240, splits, models)."""
    return local_build / "dataset"

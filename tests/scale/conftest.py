"""A tiny capture built once with the local executor: the reference the Ray builds must reproduce byte for byte.

The scene and picks are those of tests/build/test_build_dataset.py (a 12-frame 320x240 orbit round a 2 m
block; picks with 2 cm noise make the alignment fast and independent of the global registration).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from sim_testdata import write_picks_from_truth, write_tiny_scene

EDITS = (("width = 160", "width = 320"), ("height = 120", "height = 240"), ("speed_mps = 0.5", "speed_mps = 0.3"),
         ("radius_m = 3.2", "radius_m = 3.0"), ("size_m = [1.2, 0.8, 0.6]", "size_m = [2.0, 1.4, 1.2]"),
         ("position = [0.0, 0.0, 0.3]", "position = [0.0, 0.0, 0.0]"),
         ("center = [0.0, 0.0, 0.5]", "center = [0.0, 0.0, 0.8]"),
         ("position = [-1.0, 0.9, 0.0]", "position = [-0.6, 0.0, 1.2]"),
         ("position = [0.9, -0.8, 0.1]", "position = [0.6, -0.3, 1.2]"))


@pytest.fixture(scope="session")
def scale_capture(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> tuple[Path, Path]:
    """(scene spec, simulator output) of a 12-frame 320x240 orbit, no water effects."""
    from cadalign.sim.run import simulate

    root = tmp_path_factory.mktemp("scale_capture")
    spec = write_tiny_scene(root / "tiny.toml", effects=[], frames=12)
    text = spec.read_text()
    for a, b in EDITS:
        text = text.replace(a, b)
    spec.write_text(text)
    return spec, simulate(spec, root / "sim", video=False, contact_sheet=False)


@pytest.fixture(scope="session")
def local_build(scale_capture: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """OUT of ``build_dataset(..., executor=None)`` (sfm/, align/, dataset/, picks.json)."""
    from cadalign.build_dataset import build_dataset
    from cadalign.sfm import PRESETS, run

    spec, sim = scale_capture
    out = tmp_path_factory.mktemp("local_build")
    sfm_dir = run(PRESETS["fast"], sim / "frames", out / "sfm")
    write_picks_from_truth(sfm_dir, sim, out / "picks.json")
    return build_dataset(sim / "frames", spec, out, preset="fast", picks=out / "picks.json")


@pytest.fixture(scope="session")
def ddp_scene(local_build: Path) -> Path:
    """The dataset the DDP tests train on: the reference build (12 frames, 320x240, splits, models)."""
    return local_build / "dataset"

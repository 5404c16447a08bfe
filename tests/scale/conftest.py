"""A tiny capture built once with the local executor: the reference the Ray builds must reproduce byte for byte.

The scene and picks are those of tests/build/test_build_dataset.py (a 12-frame 320x240 orbit round a 2 m
block; picks with 2 cm noise make the alignment fast and independent of the global registration).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from sim_testdata import write_tiny_scene

from cadalign.io import read_json, write_json

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
    from cadalign.eval.dataset_eval import true_cad_from_sfm
    from cadalign.sfm import PRESETS, run

    spec, sim = scale_capture
    out = tmp_path_factory.mktemp("local_build")
    sfm_dir = run(PRESETS["fast"], sim / "frames", out / "sfm")
    true = true_cad_from_sfm(read_json(sfm_dir / "cameras.json")["frames"],
                             read_json(sim / "gt" / "sim" / "000000" / "cameras.json")["frames"])
    cad_pts = np.array([[1.0, 0.7, 1.2], [-1.0, -0.7, 1.2], [1.0, -0.7, 0.0], [-1.0, 0.7, 0.0]])
    noisy = cad_pts + np.random.default_rng(0).normal(0, 0.02, cad_pts.shape)
    sfm_pts = true.inverse().apply(noisy)
    write_json(out / "picks.json", {"pairs": [{"sfm": s.tolist(), "cad_m": c.tolist()}
                                              for s, c in zip(sfm_pts, cad_pts, strict=True)]})
    return build_dataset(sim / "frames", spec, out, preset="fast", picks=out / "picks.json")


@pytest.fixture(scope="session")
def ddp_scene(local_build: Path) -> Path:
    """The dataset the DDP tests train on: the reference build (12 frames, 320x240, splits, models)."""
    return local_build / "dataset"

"""A known calibration set after self-calibrated mapping (``camera.known_intrinsics_from='refinement'``)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from sfm_synthetic import synthetic_model

from cadalign.errors import InputError
from cadalign.evaluate.sfm import pose_errors
from cadalign.sfm.config import PRESETS
from cadalign.sfm.refine import refine
from cadalign.sfm.report import cameras_json, intrinsics_from_cameras_json

TRUE_K = (300.0, 300.0, 160.0, 120.0)


def _ba(rec: pycolmap.Reconstruction, refine_focal: bool) -> None:
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.refine_focal_length = refine_focal
    opts.refine_extra_params = refine_focal
    opts.refine_principal_point = False
    pycolmap.bundle_adjustment(rec, opts)


@pytest.fixture()
def long_focal_model(tmp_path: Path) -> tuple[pycolmap.Reconstruction, pycolmap.Reconstruction]:
    """(truth, a model adjusted to a focal length 2 % too long, as self-calibration on a critical motion gives)."""
    truth = synthetic_model(tmp_path / "database.db", frames=8, points=300, seed=5)
    wrong = pycolmap.Reconstruction(truth)
    for cam in wrong.cameras.values():
        cam.params = [306.0, 160.0, 120.0, 0.0]
    _ba(wrong, refine_focal=False)
    return truth, wrong


def _cfg(known_from: str):
    base = PRESETS["fast"]
    camera = dataclasses.replace(base.camera, intrinsics=TRUE_K, known_intrinsics_from=known_from)
    return dataclasses.replace(base, camera=camera, num_threads=1)


def _centre_rmse(rec: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> float:
    pe = pose_errors(cameras_json(rec), cameras_json(truth))
    return float(np.sqrt(np.mean(pe.centre_err_m**2)))


def test_known_calibration_replaces_the_self_calibrated_camera_and_fixes_the_poses(long_focal_model):
    truth, wrong = long_focal_model
    before = _centre_rmse(wrong, truth)
    out = refine(wrong, _cfg("refinement"))
    cam = next(iter(wrong.cameras.values()))
    assert cam.model.name == "PINHOLE"
    np.testing.assert_allclose(cam.params, TRUE_K)  # held fixed through the adjustment
    assert out["known_intrinsics_set"]["1"]["params_before"][0] == pytest.approx(306.0)
    assert out["after"]["reprojection_px"] < 0.05
    after = _centre_rmse(wrong, truth)
    assert after < 0.2 * before, (before, after)


def test_calibration_fixed_from_mapping_is_left_to_the_mapper(long_focal_model):
    _, wrong = long_focal_model
    out = refine(wrong, _cfg("mapping"))
    cam = next(iter(wrong.cameras.values()))
    assert "known_intrinsics_set" not in out
    assert cam.model.name == "SIMPLE_RADIAL" and cam.params[0] == pytest.approx(306.0)  # not touched


@pytest.mark.parametrize("content", [
    {"K": [450.0, 0, 321.0, 0, 452.0, 239.0, 0, 0, 1]},
    {"K": [[450.0, 0, 321.0], [0, 452.0, 239.0], [0, 0, 1]], "width": 640, "height": 480},
    {"frames": {"a.png": {"K": [450.0, 0, 321.0, 0, 452.0, 239.0, 0, 0, 1]}}},
])
def test_calibration_files_in_every_accepted_form(tmp_path: Path, content: dict):
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(content))
    assert intrinsics_from_cameras_json(path) == (450.0, 452.0, 321.0, 239.0)


@pytest.mark.parametrize("content", [{}, {"K": [1, 2, 3]}, {"K": [0, 0, 320, 0, 450, 240, 0, 0, 1]},
                                     {"K": [float("nan")] * 9}])
def test_bad_calibration_files_name_the_file_and_the_format(tmp_path: Path, content: dict):
    path = tmp_path / "calib.json"
    path.write_text(json.dumps(content))
    with pytest.raises(InputError, match="calib.json"):
        intrinsics_from_cameras_json(path)

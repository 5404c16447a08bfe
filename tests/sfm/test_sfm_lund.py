"""Real images: OpenSfM's Lund street sequence (29 JPEGs, 1024x768) registers in one model.

Takes 55-90 s on 2 cores (features ~20 s, matching ~30-40 s), hence ``slow``:
``pytest -m slow tests/sfm/test_sfm_lund.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cadalign.config import resolve
from cadalign.sfm import PRESETS, SfMConfig, run


@pytest.mark.slow
def test_lund_registers_all_29_images(shared_data: Path, tmp_path: Path):
    images = shared_data / "opensfm_lund" / "images"
    if not images.is_dir():
        pytest.fail(f"{images} is missing; it is part of the shared test data")
    out = run(resolve(SfMConfig, PRESETS, "balanced"), images, tmp_path / "lund")
    report = json.loads((out / "sfm_report.json").read_text())
    assert report["frames_in"] == 29
    assert report["registered"] == 29, report["unregistered"]
    assert len(report["models"]) == 1 or report["models"][1]["registered"] < 3
    assert report["mean_reprojection_error_px"] < 1.0
    assert len(json.loads((out / "cameras.json").read_text())["frames"]) == 29

"""Plain pycolmap, the SfM benches' baseline (cadalign.sfm.plain), and the bench's scoring of it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cadalign.bench.sweeps.sfm import plain_measure
from cadalign.sfm.plain import STEPS, run_plain


def test_plain_pycolmap_maps_the_frames_and_times_each_step(tiny_dive: Path, tmp_path: Path):
    work = tmp_path / "plain"
    (work / "stale").mkdir(parents=True)  # the work folder is emptied first
    res = run_plain(tiny_dive / "frames", work, num_threads=1)
    assert res.frames == 10 and not (work / "stale").exists()
    assert set(res.seconds) == {*STEPS, "total"}
    assert res.seconds["total"] == sum(res.seconds[s] for s in STEPS) > 0
    assert res.registered >= 8
    assert len(res.model.cameras) == 1  # one shared camera, as one video's frames have


def test_the_bench_scores_plain_pycolmap_against_the_simulators_cameras(tiny_dive: Path, tmp_path: Path):
    m = plain_measure(tiny_dive, tmp_path / "plain", seed=0)
    assert 0.8 <= m["registration_rate"] <= 1.0
    assert 0 <= m["rel_rot_err_deg"] < 1.0 and np.isfinite(m["centre_rmse_m"])
    assert m["sfm_s"] == pytest.approx(m["features_s"] + m["matches_s"] + m["mapping_s"])

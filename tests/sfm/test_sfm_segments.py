"""Long surveys: overlapping SfM segments mapped separately and merged into one model."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.sfm.segments import plan_segments

runner = CliRunner()


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 400), st.integers(4, 60), st.data())
def test_segments_cover_every_frame_with_the_overlap_asked(n: int, length: int, data: st.DataObject):
    overlap = data.draw(st.integers(3, length - 1))
    windows = plan_segments(n, length, overlap)
    assert windows[0].start == 0 and windows[-1].stop == n
    assert set().union(*map(set, windows)) == set(range(n))
    assert all(len(w) == min(n, length) for w in windows)
    for a, b in zip(windows, windows[1:], strict=False):
        assert a.start < b.start and len(set(a) & set(b)) >= overlap
    if len(windows) > 2:  # the fewest windows: one less could not keep the overlap
        assert (len(windows) - 2) * (length - overlap) + length < n


def test_an_overlap_below_three_frames_is_refused():
    with pytest.raises(ValueError, match=">= 3"):
        plan_segments(100, 10, 2)


@pytest.fixture(scope="module")
def segmented(tiny_dive: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sfm_seg") / "out"
    res = runner.invoke(app, ["sfm", str(tiny_dive / "frames"), "--out", str(out), "--gt", str(tiny_dive),
                              "--set", "num_threads=1", "--set", "mapper.segment_frames=6",
                              "--set", "mapper.segment_overlap=3"])
    assert res.exit_code == 0, res.output
    return out


def test_merged_segments_register_every_frame_as_accurately_as_one_model(segmented: Path):
    report = json.loads((segmented / "sfm_report.json").read_text())
    assert report["mapper"] == "segments"
    seg = report["segments"]
    assert [s["frames"] for s in seg["segments"]] == [["000000.png", "000005.png"], ["000002.png", "000007.png"],
                                                       ["000004.png", "000009.png"]]
    assert all(s["registered"] == 6 for s in seg["segments"])
    assert len(seg["seams"]) == 2 and all(s["shared_frames"] >= 3 for s in seg["seams"])
    assert all(s["centre_gap_steps_median"] < 0.05 for s in seg["seams"])  # the segments agree where they meet
    gt = report["gt"]
    assert report["registered"] == 10 and gt["registration_rate"] == 1.0
    # the same bounds as the one-model run of tests/sfm/test_sfm_pipeline.py
    assert gt["rel_rot_err_deg_mean"] < 0.3 and gt["centre_rmse_rel"] < 0.01
    assert report["consistency"]["breaks"] == []
    # tracks run across the seams: points are seen from frames of different segments
    assert report["mean_track_length"] > 2.5

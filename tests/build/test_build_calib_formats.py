"""Issue 46: ``build-dataset --calib`` gives the same dataset for the same camera in two formats (the simulator's
``{"K"}`` JSON and a ROS CameraInfo YAML), and its output holds no COLMAP log lines and no numpy reprs.

Two tiny builds take ~45 s on a loaded 2-core machine: marked slow (the fast suite checks identical parsed
cameras, SfM settings and prepared frames across all five formats in tests/formats)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from calib_testdata import write_all
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.io import read_json
from cadalign.testing.tiny_scene import write_build_capture, write_picks_from_truth

GLOG_LINE = re.compile(r"^[IWE]\d{8} ", re.MULTILINE)
runner = CliRunner()


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> tuple[Path, Path]:
    from cadalign.sim.run import simulate

    root = tmp_path_factory.mktemp("calib_capture")
    spec = write_build_capture(root / "tiny.toml", effects=[], frames=10)
    return spec, simulate(spec, root / "sim", video=False, contact_sheet=False)


def _build(spec: Path, sim: Path, calib: Path, out: Path, capfd: pytest.CaptureFixture[str]) -> str:
    common = ["--preset", "fast", "--calib", str(calib)]
    res = runner.invoke(app, ["sfm", str(sim / "frames"), "--out", str(out / "sfm"), *common,
                              "--set", "num_threads=1"])
    assert res.exit_code == 0, res.output
    write_picks_from_truth(out / "sfm", sim, out / "picks.json")
    res = runner.invoke(app, ["build-dataset", str(sim / "frames"), "--cad", str(spec), "--out", str(out), *common,
                              "--init", str(out / "picks.json"), "--gt", str(sim), "--sfm-set", "num_threads=1"])
    captured = capfd.readouterr()
    assert res.exit_code == 0, res.output + captured.err[-3000:]
    return res.output + captured.out + captured.err


@pytest.mark.slow
def test_build_dataset_is_the_same_for_the_calibration_in_two_formats(capture: tuple[Path, Path], tmp_path: Path,
                                                                      capfd: pytest.CaptureFixture[str]) -> None:
    spec, sim = capture
    cal = read_json(sim / "calibration.json")
    ros = write_all(tmp_path / "calib", np.reshape(cal["K"], (3, 3)), cal["width"], cal["height"])["ros"]
    outs = {}
    for name, calib in (("K-json", sim / "calibration.json"), ("ros", ros)):
        text = _build(spec, sim, calib, tmp_path / name, capfd)
        assert not GLOG_LINE.search(text), GLOG_LINE.findall(text)[:3]
        assert "np.float64(" not in text
        outs[name] = tmp_path / name / "dataset" / "all" / "000000"
        report = read_json(tmp_path / name / "build_report.json")
        assert report["colmap_log"]["shown_not_counted"] is False
        assert (outs[name] / "trajectory.tum").is_file() and (tmp_path / name / "sfm" / "trajectory.tum").is_file()
    for f in ("scene_camera.json", "scene_gt.json"):
        assert read_json(outs["K-json"] / f) == read_json(outs["ros"] / f), f

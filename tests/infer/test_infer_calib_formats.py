"""Issue 46: ``infer --calib`` reads every calibration format (the ``{"K"}`` JSON it used to refuse included), and the
same camera in any format gives the same poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from calib_testdata import write_all
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.io import read_json

runner = CliRunner()


def test_infer_gives_the_same_poses_for_the_calibration_in_any_format(tiny_sim: Path, tmp_path: Path) -> None:
    cal = read_json(tiny_sim / "calibration.json")
    files = write_all(tmp_path / "calib", np.reshape(cal["K"], (3, 3)), cal["width"], cal["height"])
    runs = {}
    for fmt in ("K-json", "ros", "colmap-cameras.txt", "opencv", "cameras.json"):
        calib = tiny_sim / "calibration.json" if fmt == "K-json" else files[fmt]  # the simulator's own file first
        out = tmp_path / fmt
        res = runner.invoke(app, ["infer", str(tiny_sim / "frames"), "--oracle-gt", str(tiny_sim), "--cad",
                                  str(tiny_sim.parent / "tiny.toml"), "--out", str(out), "--calib", str(calib),
                                  "--max-frames", "2"])
        assert res.exit_code == 0, res.output
        assert "np.float64(" not in res.output
        runs[fmt] = (out / "poses.jsonl").read_text()
        record = read_json(out / "calibration.json")
        assert record["undistorted"] is False and record["width"] == cal["width"]
    assert runs["K-json"].strip()  # poses were found
    assert all(text == runs["K-json"] for text in runs.values())


def test_infer_refuses_a_calibration_for_another_size(tiny_sim: Path, tmp_path: Path) -> None:
    cal = read_json(tiny_sim / "calibration.json")
    K2 = np.diag([2.0, 2.0, 1.0]) @ np.reshape(cal["K"], (3, 3))  # the same lens at twice the resolution
    ros = write_all(tmp_path, K2, 2 * cal["width"], 2 * cal["height"])["ros"]
    res = runner.invoke(app, ["infer", str(tiny_sim / "frames"), "--oracle-gt", str(tiny_sim), "--cad",
                              str(tiny_sim.parent / "tiny.toml"), "--out", str(tmp_path / "o"), "--calib", str(ros),
                              "--max-frames", "1"])
    out = "".join(res.output.split())
    assert res.exit_code == 1 and "Traceback" not in out
    assert "ros_camera_info.yaml" in out and f"{2 * cal['width']}x{2 * cal['height']}" in out

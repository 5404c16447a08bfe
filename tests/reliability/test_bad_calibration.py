"""Bad ``--calib`` files (issue 46): the project's error naming the file and the fix, never a traceback.

Each case runs through the library (recorded in the bad-input catalogue) and the CLI (exit code 1, one line).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from reliability_testdata import expect_error
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.errors import InputError
from cadalign.io import read_json

runner = CliRunner()


def _frames(tiny_bop: Path) -> Path:
    return tiny_bop / "rgb"


def _cli_fails(args: list[str], *fragments: str) -> None:
    res = runner.invoke(app, args)
    out = "".join(res.output.split())  # rich wraps long lines, even inside a path
    assert res.exit_code == 1, res.output
    assert "error:" in out and "Traceback" not in out
    for frag in fragments:
        assert "".join(frag.split()) in out, (frag, res.output)


def _calibration_for(tiny_bop: Path, width: int, height: int) -> dict:
    K = np.reshape(read_json(tiny_bop / "scene_camera.json")["0"]["cam_K"], (3, 3))
    return {"K": K.ravel().tolist(), "width": width, "height": height}


def test_calibration_for_another_image_size(tiny_bop: Path, tmp_path: Path) -> None:
    from cadalign.infer.run import load_calibration
    from cadalign.sfm.known_camera import checked_calibration

    path = tmp_path / "calib_640.json"
    path.write_text(json.dumps(_calibration_for(tiny_bop, 640, 480)))
    expect_error("sfm / build-dataset", "--calib made for 640x480, frames 160x120", InputError,
                 lambda: checked_calibration(path, _frames(tiny_bop)), "calib_640.json", "640x480", "160x120",
                 "pass the calibration made for this camera's resolution")
    expect_error("infer", "--calib made for 640x480, frames 160x120", InputError,
                 lambda: list(load_calibration(path).frames(_frames(tiny_bop), 1)), "calib_640.json", "160x120")
    _cli_fails(["sfm", str(_frames(tiny_bop)), "--out", str(tmp_path / "o"), "--calib", str(path)],
               "calib_640.json", "640x480", "160x120")


@pytest.mark.parametrize(("name", "text", "fragments"), [
    ("lens.cal", "camera: rov\nfocal: 260\n", ["lens.cal", "no 'camera_matrix'"]),
    ("lens.txt", "this is a lens report, not a calibration\n", ["lens.txt", "no known calibration format"]),
    ("lens.bin", "\x00\x01\x02garbage", ["lens.bin", "no known format"]),
])
def test_calibration_in_an_unknown_format(tmp_path: Path, tiny_bop: Path, name: str, text: str,
                                          fragments: list[str]) -> None:
    from cadalign.formats.calibration import read_calibration

    path = tmp_path / name
    path.write_text(text)
    expect_error("--calib", f"a file in no calibration format ({name})", InputError, lambda: read_calibration(path),
                 *fragments, "fix the calibration file")
    _cli_fails(["sfm", str(_frames(tiny_bop)), "--out", str(tmp_path / "o"), "--calib", str(path)], *fragments)


def test_opencv_yaml_without_camera_matrix(tmp_path: Path, tiny_bop: Path) -> None:
    from cadalign.formats.calibration import read_calibration

    plain = tmp_path / "checkerboard.yaml"
    plain.write_text("image_width: 160\nimage_height: 120\ndistortion_coefficients: [0.1, 0.0, 0.0, 0.0, 0.0]\n")
    opencv = tmp_path / "opencv.yaml"
    opencv.write_text("%YAML:1.0\n---\nimage_width: 160\nimage_height: 120\n"
                      "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
                      "   data: [ 0.1, 0., 0., 0., 0. ]\n")
    for path in (plain, opencv):
        expect_error("--calib", f"a YAML calibration without camera_matrix ({path.name})", InputError,
                     lambda p=path: read_calibration(p), path.name, "camera_matrix", "fix the calibration file")
    _cli_fails(["sfm", str(_frames(tiny_bop)), "--out", str(tmp_path / "o"), "--calib", str(opencv)],
               "opencv.yaml", "camera_matrix")

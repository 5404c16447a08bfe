"""One reader behind every ``--calib`` (issue 46): five formats, one camera; pixel centres; distortion; bad files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from calib_testdata import write_all

from cadalign.errors import InputError
from cadalign.formats.calibration import Undistorter, read_calibration, undistort_maps
from cadalign.io import read_image, read_json

K = np.array([[260.0, 0.0, 160.0], [0.0, 262.0, 120.0], [0.0, 0.0, 1.0]])  # cadalign convention (+0.5)
DIST = (-0.28, 0.09, 0.0012, -0.0008, -0.012)


@pytest.mark.parametrize("dist", [(), DIST])
def test_five_formats_give_the_same_camera(tmp_path: Path, dist: tuple[float, ...]) -> None:
    files = write_all(tmp_path, K, 320, 240, dist)
    cals = {fmt: read_calibration(p) for fmt, p in files.items()}
    for fmt, c in cals.items():
        assert c.format == fmt and c.source == files[fmt]
        np.testing.assert_allclose(c.K, K, rtol=0, atol=1e-12, err_msg=fmt)
        assert (c.width, c.height) == (320, 240)
    assert {(c.distortion_model, c.distortion) for c in cals.values()} == {("opencv", dist) if dist else ("none", ())}


def test_opencv_and_ros_centres_are_shifted_by_half_a_pixel(tmp_path: Path) -> None:
    files = write_all(tmp_path, K, 320, 240)
    text = files["opencv"].read_text()
    assert "159.5" in text and "119.5" in text  # as OpenCV writes it: pixel centres at integers
    assert read_calibration(files["opencv"]).intrinsics == (260.0, 262.0, 160.0, 120.0)
    assert read_calibration(files["colmap-cameras.txt"]).intrinsics == (260.0, 262.0, 160.0, 120.0)  # COLMAP = ours


def test_opencv_xml_and_yaml_1_0_as_older_opencv_writes(tmp_path: Path) -> None:
    yaml10 = tmp_path / "cam.yml"
    yaml10.write_text("%YAML:1.0\n---\nimage_width: 320\nimage_height: 240\ncamera_matrix: !!opencv-matrix\n"
                      "   rows: 3\n   cols: 3\n   dt: d\n   data: [ 260., 0., 159.5, 0., 262., 119.5, 0., 0., 1. ]\n"
                      "dist_coeff: !!opencv-matrix\n   rows: 5\n   cols: 1\n   dt: d\n"
                      "   data: [ -0.28, 0.09, 0.0012, -0.0008, -0.012 ]\n")
    xml = tmp_path / "cam.xml"
    xml.write_text('<?xml version="1.0"?>\n<opencv_storage>\n<image_width>320</image_width>\n'
                   "<image_height>240</image_height>\n<camera_matrix type_id=\"opencv-matrix\">\n  <rows>3</rows>\n"
                   "  <cols>3</cols>\n  <dt>d</dt>\n  <data>260. 0. 159.5 0. 262. 119.5 0. 0. 1.</data>"
                   "</camera_matrix>\n"
                   '<distortion_coefficients type_id="opencv-matrix">\n  <rows>1</rows>\n  <cols>5</cols>\n'
                   "  <dt>d</dt>\n  <data>-0.28 0.09 0.0012 -0.0008 -0.012</data></distortion_coefficients>\n"
                   "</opencv_storage>\n")
    for path in (yaml10, xml):
        c = read_calibration(path)
        assert c.format == "opencv" and c.intrinsics == (260.0, 262.0, 160.0, 120.0)
        assert (c.width, c.height, c.distortion_model, c.distortion) == (320, 240, "opencv", DIST)


def test_the_simulators_calibration_json_reads_unchanged(small_sim: Path) -> None:
    c = read_calibration(small_sim / "calibration.json")
    np.testing.assert_array_equal(c.K.ravel(), read_json(small_sim / "calibration.json")["K"])
    assert c.format == "K-json" and c.distortion_model == "none" and (c.width, c.height) == (320, 240)


def test_undistortion_maps_match_opencv_projection_within_a_hundredth_pixel() -> None:
    """Output pixel (x, y) (centre x + 0.5, y + 0.5 in cadalign's convention) must sample the distorted image where
    OpenCV's lens model sends the pinhole ray through that centre."""
    import cv2

    w, h = 320, 240
    m1, m2 = undistort_maps(K, "opencv", DIST, w, h)
    ys, xs = np.mgrid[0:h:7, 0:w:7]
    centres = np.stack([xs.ravel() + 0.5, ys.ravel() + 0.5], axis=1)  # ours
    rays = np.linalg.solve(K, np.c_[centres, np.ones(len(centres))].T).T
    K_cv = K.copy()
    K_cv[:2, 2] -= 0.5
    proj, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K_cv, np.asarray(DIST))
    sampled = np.stack([m1[ys.ravel(), xs.ravel()], m2[ys.ravel(), xs.ravel()]], axis=1)  # OpenCV pixel coords
    assert np.abs(sampled - proj.reshape(-1, 2)).max() < 0.01


def _distort(image: np.ndarray, K_cv: np.ndarray, dist: tuple[float, ...]) -> np.ndarray:
    """What a lens with ``dist`` records of the pinhole ``image``: each distorted pixel samples the pinhole image
    where cv2.undistortPoints sends it (OpenCV convention throughout)."""
    import cv2

    h, w = image.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.stack([xs.ravel(), ys.ravel()], axis=1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(pts, K_cv, np.asarray(dist), R=None, P=K_cv,
                                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)).reshape(h, w, 2)
    return cv2.remap(image, ideal[..., 0].astype(np.float32), ideal[..., 1].astype(np.float32), cv2.INTER_CUBIC,
                     borderMode=cv2.BORDER_REFLECT)


def test_distorted_frames_undistort_back_to_the_pinhole_truth(small_sim: Path, tmp_path: Path) -> None:
    """The sim frame (pinhole truth) distorted by a known lens, undistorted through a ROS calibration of that lens:
    the sub-pixel shift to the truth (phase correlation, central crop) is below 0.1 px."""
    import cv2

    truth = read_image(sorted((small_sim / "frames").glob("*.png"))[0])
    h, w = truth.shape[:2]
    K_sim = np.reshape(read_json(small_sim / "calibration.json")["K"], (3, 3))
    K_cv = K_sim.copy()
    K_cv[:2, 2] -= 0.5
    dist = (-0.25, 0.06, 0.001, -0.001, 0.0)
    distorted = _distort(truth, K_cv, dist)
    cal = read_calibration(write_all(tmp_path, K_sim, w, h, dist)["ros"])
    restored = Undistorter.of(cal)(distorted)

    def shift(a: np.ndarray, b: np.ndarray, y0: float, x0: float) -> float:
        """Sub-pixel translation between two images in a crop (ECC; phase correlation is biased by 0.5 px on
        some crop sizes in OpenCV 5)."""
        crop = (slice(int(y0 * h), int((y0 + 0.35) * h)), slice(int(x0 * w), int((x0 + 0.35) * w)))
        ga, gb = (cv2.cvtColor(im, cv2.COLOR_RGB2GRAY)[crop].astype(np.float32) for im in (a, b))
        crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-7)
        _, warp = cv2.findTransformECC(ga, gb, np.eye(2, 3, dtype=np.float32), cv2.MOTION_TRANSLATION, crit, None, 5)
        return float(np.hypot(*warp[:, 2]))

    crops = [(y0, x0) for y0 in (0.08, 0.33, 0.57) for x0 in (0.08, 0.33, 0.57)]
    after = {c: shift(truth, restored, *c) for c in crops}
    print(f"undistorted vs pinhole truth: max shift {max(after.values()):.4f} px over {len(after)} crops")
    assert max(after.values()) < 0.1, after
    assert max(shift(truth, distorted, *c) for c in crops) > 1.0  # the lens really moved the image


def test_identical_prepared_frames_and_sfm_settings_from_every_format(small_sim: Path, tmp_path: Path) -> None:
    """The same camera in five formats -> the same SfM settings (fingerprint) and bitwise the same prepared
    (undistorted) frames in SfM and in infer."""
    from cadalign.infer.run import load_calibration
    from cadalign.sfm import PRESETS
    from cadalign.sfm.frames import extract_frames
    from cadalign.sfm.known_camera import with_calibration
    from cadalign.sfm.pipeline import undistorter

    K_sim = np.reshape(read_json(small_sim / "calibration.json")["K"], (3, 3))
    files = write_all(tmp_path / "calib", K_sim, 320, 240, (-0.2, 0.05, 0.0, 0.0))
    cfgs, frames, infer_frames = [], [], []
    for fmt, path in files.items():
        cfg = with_calibration(PRESETS["fast"], path, small_sim / "frames")
        cfgs.append(cfg)
        out = tmp_path / fmt
        extract_frames(small_sim / "frames", cfg.frames, out / "images", out / "masks", undistort=undistorter(cfg))
        frames.append([read_image(p) for p in sorted((out / "images").glob("*.png"))])
        cal = load_calibration(path)
        infer_frames.append([vf.image for vf in cal.frames(small_sim / "frames", 2)])
        np.testing.assert_allclose(cal.K("000000.png"), K_sim, atol=1e-12)
    assert all(c == cfgs[0] for c in cfgs) and cfgs[0].camera.distortion == (-0.2, 0.05, 0.0, 0.0)
    raw = read_image(sorted((small_sim / "frames").glob("*.png"))[0])
    assert not np.array_equal(frames[0][0], raw)  # undistorted, not copied
    for other in frames[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(frames[0], other, strict=True))
    for other in infer_frames[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(infer_frames[0], other, strict=True))


def test_frames_json_records_the_undistortion(small_sim: Path, tmp_path: Path) -> None:
    from cadalign.sfm import PRESETS
    from cadalign.sfm.known_camera import with_calibration
    from cadalign.sfm.pipeline import Layout, _step_frames

    path = write_all(tmp_path / "c", np.reshape(read_json(small_sim / "calibration.json")["K"], (3, 3)), 320, 240,
                     (-0.2, 0.05))["ros"]
    cfg = with_calibration(PRESETS["fast"], path, small_sim / "frames")
    _step_frames(cfg, small_sim / "frames", Layout(tmp_path / "sfm"), None, None)
    rec = read_json(tmp_path / "sfm" / "frames.json")["undistorted"]
    assert rec["model"] == "opencv" and rec["coeffs"] == [-0.2, 0.05, 0.0, 0.0]


@pytest.mark.parametrize(("name", "text", "fragments"), [
    ("cam.json", json.dumps({"camera_matrix": [1, 2]}), ["cam.json", "neither 'K' nor"]),
    ("cam.txt", "fx=260 fy=262\n", ["cam.txt", "no known calibration format"]),
    ("cam.yaml", "image_width: 320\nimage_height: 240\nD: [0, 0, 0, 0, 0]\n", ["cam.yaml", "no 'camera_matrix'"]),
    ("cameras.txt", "1 PINHOLE 320 240 260 262 160 120\n2 PINHOLE 640 480 520 524 320 240\n",
     ["cameras.txt", "2 different cameras"]),
    ("cameras.txt", "1 FOV 320 240 260 262 160 120 0.1\n", ["cameras.txt", "FOV is not supported"]),
    ("ros.yaml", "camera_matrix: {rows: 3, cols: 3, data: [260, 0, 160, 0, 262, 120, 0, 0, 1]}\n"
     "distortion_model: equidistant\ndistortion_coefficients: {data: [0.1, 0.2]}\n", ["ros.yaml", "'fisheye'"]),
])
def test_bad_calibration_files_name_the_file_and_the_fix(tmp_path: Path, name: str, text: str,
                                                          fragments: list[str]) -> None:
    (tmp_path / name).write_text(text)
    with pytest.raises(InputError) as info:
        read_calibration(tmp_path / name)
    for frag in fragments:
        assert frag in str(info.value)
    assert "fix" in str(info.value) or "keep" in str(info.value)


def test_size_check_names_the_file_both_sizes_and_the_fix(tmp_path: Path) -> None:
    c = read_calibration(write_all(tmp_path, K, 320, 240)["ros"])
    c.check_size(320, 240, "frame a.png")
    with pytest.raises(InputError, match=r"ros_camera_info.yaml is a calibration for 320x240 .* 640x480; pass"):
        c.check_size(640, 480, "frame a.png")


def test_a_cameras_json_gives_each_posed_frame_s_camera_pose() -> None:
    """``camera_pose_arrays``: the frames with a pose, sorted (or as named), their ``R_cam_from_world`` and
    translations; a frame with intrinsics only is left out. ``frame_pose`` gives one frame's ``T_cam_from_world``."""
    from cadalign.formats.calibration import camera_pose_arrays, frame_pose
    from cadalign.geometry.rotations import axis_angle_to_matrix

    R = axis_angle_to_matrix(np.array([0.1, -0.2, 0.3]))
    cams = {"units": "sfm", "frames": {
        "b.png": {"K": np.eye(3).tolist(), "R_cam_from_world": R.tolist(), "t_cam_from_world_m": [1.0, 2.0, 3.0]},
        "a.png": {"K": np.eye(3).tolist(), "R_cam_from_world": np.eye(3).ravel().tolist(),
                  "t_cam_from_world_m": [0, 0, 1]},
        "c.png": {"K": np.eye(3).tolist()}}}
    names, Rs, ts = camera_pose_arrays(cams)
    assert names == ["a.png", "b.png"] and Rs.shape == (2, 3, 3) and ts.shape == (2, 3)
    assert np.allclose(Rs[1], R) and np.allclose(ts, [[0, 0, 1], [1, 2, 3]])
    names, Rs, ts = camera_pose_arrays(cams, ["b.png"])
    assert names == ["b.png"] and np.allclose(ts, [[1, 2, 3]])
    T = frame_pose(cams["frames"]["b.png"])
    assert np.allclose(T.apply(-R.T @ [1.0, 2.0, 3.0]), 0.0)  # the camera centre maps to the origin
    assert camera_pose_arrays({"frames": {}})[1].shape == (0, 3, 3)

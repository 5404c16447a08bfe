"""Bad-input catalogue: each bad input a user can hand a stage gives the project's error naming it and the fix.

Frames for SfM (video / image folder), CAD files, scene specs, BOP scenes and config files. Each case
records the exact message in the catalogue (see ``conftest.py`` for writing it as a table).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh
from reliability_testdata import expect_error, expect_warning

from cadalign.cad import load_cad
from cadalign.cad.units import check_unit
from cadalign.config import read_mapping, resolve
from cadalign.errors import ConfigError, DegenerateGeometryError, InputError, UnitError
from cadalign.formats.bop import BopScene
from cadalign.io import write_image
from cadalign.sfm.config import PRESETS as SFM_PRESETS
from cadalign.sfm.config import FrameConfig, SfMConfig
from cadalign.sfm.frames import extract_frames, select_frames
from cadalign.sim.spec import load_scene, resolve_source
from cadalign.testing.tiny_scene import write_tiny_scene
from cadalign.types import Camera, Rigid3, Sim3

W, H = 96, 72


def _texture(seed: int, w: int = W, h: int = H) -> np.ndarray:
    """A seeded, sharp RGB frame (random blocks) that SfM frame checks accept."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (h // 4, w // 4, 3), dtype=np.uint8)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)


def _extract(src: Path, tmp_path: Path, cfg: FrameConfig | None = None) -> list:
    cfg = cfg or FrameConfig(enhance="none", blur_ratio=0.0, min_motion=0.0)
    return extract_frames(src, cfg, tmp_path / "images", tmp_path / "masks")


def _write_video(path: Path, frames: list[np.ndarray]) -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    assert writer.isOpened()
    for f in frames:
        writer.write(np.ascontiguousarray(f[..., ::-1]))
    writer.release()
    return path


# ----------------------------------------------------------------------------------------------- video / images


def test_missing_video(tmp_path: Path) -> None:
    expect_error("sfm frames", "missing video path", InputError, lambda: _extract(tmp_path / "dive.mp4", tmp_path),
                 "input not found", "dive.mp4", "pass an existing video")


def test_zero_length_video(tmp_path: Path) -> None:
    (tmp_path / "dive.mp4").write_bytes(b"")
    expect_error("sfm frames", "zero-length video (0 bytes)", InputError,
                 lambda: _extract(tmp_path / "dive.mp4", tmp_path), "dive.mp4", "is empty (0 bytes)")


def test_corrupt_video(tmp_path: Path) -> None:
    (tmp_path / "dive.mp4").write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    msg = expect_error("sfm frames", "corrupt video (random bytes)", InputError,
                       lambda: _extract(tmp_path / "dive.mp4", tmp_path), "dive.mp4")
    assert "could not open video" in msg or "no frame could be decoded" in msg


def test_video_truncated_to_its_header(tmp_path: Path) -> None:
    path = _write_video(tmp_path / "dive.avi", [_texture(k) for k in range(4)])
    path.write_bytes(path.read_bytes()[:300])
    msg = expect_error("sfm frames", "video truncated to its first 300 bytes", InputError,
                       lambda: _extract(path, tmp_path), "dive.avi")
    assert "could not open video" in msg or "no frame could be decoded" in msg


def test_video_with_intact_header_and_garbage_frames(tmp_path: Path) -> None:
    path = _write_video(tmp_path / "dive.avi", [_texture(k) for k in range(4)])
    data = path.read_bytes()
    start = data.find(b"00dc") + 8  # the first frame's payload
    junk = np.random.default_rng(0).integers(0, 256, len(data) - start, dtype=np.uint8).tobytes()
    path.write_bytes(data[:start] + junk)
    msg = expect_error("sfm frames", "video with an intact header but garbage frame data", InputError,
                       lambda: _extract(path, tmp_path), "dive.avi")
    assert "no frame could be decoded" in msg or "could not open video" in msg


def test_corrupt_bag(tmp_path: Path) -> None:
    (tmp_path / "dive.bag").write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    expect_error("sfm frames", "corrupt ROS 1 bag (random bytes)", InputError,
                 lambda: _extract(tmp_path / "dive.bag", tmp_path), "dive.bag", "corrupt", "rosbag reindex")


def test_bag_truncated_mid_recording(tmp_path: Path) -> None:
    """A recording cut off before it was closed (no index at the end): named, with the reindex fix."""
    from bag_testdata import write_bag

    path = write_bag([_texture(k) for k in range(6)], tmp_path / "dive.bag", ros=1)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    expect_error("sfm frames", "ROS 1 bag truncated to half (no index)", InputError,
                 lambda: _extract(path, tmp_path), "dive.bag", "reindex")


def test_corrupt_ros2_bag_database(tmp_path: Path) -> None:
    from bag_testdata import write_bag

    bag = write_bag([_texture(k) for k in range(3)], tmp_path / "dive", ros=2)
    for db in bag.glob("*.db3"):
        db.write_bytes(b"not a database" * 100)
    expect_error("sfm frames", "ROS 2 bag with a corrupt .db3", InputError, lambda: _extract(bag, tmp_path),
                 "dive", "corrupt")


def test_bag_topic_that_does_not_exist(tmp_path: Path) -> None:
    from bag_testdata import write_bag

    from cadalign.sfm.frames import frame_candidates

    bag = write_bag([_texture(k) for k in range(3)], tmp_path / "dive.bag", ros=1, topic="/rov/cam0")
    expect_error("sfm frames", "bag topic that does not exist", InputError,
                 lambda: frame_candidates(bag, FrameConfig(), "/camera/image_raw"),
                 "/camera/image_raw is not an image topic", "dive.bag", "/rov/cam0 (sensor_msgs/msg/Image, 3",
                 "cadalign bag topics")


def test_corrupt_image_in_folder(tmp_path: Path) -> None:
    for k in range(3):
        write_image(tmp_path / "in" / f"{k:06d}.png", _texture(k))
    (tmp_path / "in" / "000001.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 50)
    expect_error("sfm frames", "corrupt PNG in a frames folder", InputError,
                 lambda: _extract(tmp_path / "in", tmp_path), "000001.png", "could not decode image",
                 "replace or remove")


def test_folder_without_images(tmp_path: Path) -> None:
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "notes.txt").write_text("dive log")
    expect_error("sfm frames", "folder with no images", InputError, lambda: _extract(tmp_path / "in", tmp_path),
                 "no images", "pass a video or a frames folder")


def test_frames_of_mixed_sizes(tmp_path: Path) -> None:
    write_image(tmp_path / "in" / "000000.png", _texture(0))
    write_image(tmp_path / "in" / "000001.png", _texture(1))
    write_image(tmp_path / "in" / "000002.png", _texture(2, 2 * W, 2 * H))
    expect_error("sfm frames", "frames of mixed sizes", InputError, lambda: _extract(tmp_path / "in", tmp_path),
                 "frames of mixed sizes", "000002.png", f"{2 * W}x{2 * H}", f"000000.png is {W}x{H}", "resize")


def test_all_black_frames_are_refused_with_their_names(tmp_path: Path) -> None:
    for k in range(3):
        write_image(tmp_path / "in" / f"{k:06d}.png", (_texture(k) // 40).astype(np.uint8))  # grey levels <= 6
    expect_error("sfm frames", "all frames black (lamps off)", InputError, lambda: _extract(tmp_path / "in", tmp_path),
                 "only 0 of 3 frames are usable", "3 black", "black: 000000.png, 000001.png, 000002.png",
                 "check the lamps")


def test_black_and_overexposed_frames_are_skipped_with_a_warning(tmp_path: Path, caplog) -> None:
    for k in range(5):
        write_image(tmp_path / "in" / f"{k:06d}.png", _texture(k))
    write_image(tmp_path / "in" / "000001.png", np.zeros((H, W, 3), np.uint8))
    write_image(tmp_path / "in" / "000003.png", np.full((H, W, 3), 250, np.uint8))
    decisions = expect_warning("sfm frames", "one black and one overexposed frame among good ones", caplog,
                               lambda: _extract(tmp_path / "in", tmp_path), "black: 000001.png",
                               "overexposed: 000003.png")
    assert [d.reason for d in decisions] == ["", "black", "", "overexposed", ""]
    assert sorted(p.name for p in (tmp_path / "images").iterdir()) == ["000000.png", "000002.png", "000004.png"]


def test_select_frames_refuses_a_non_image_candidate() -> None:
    expect_error("sfm frames", "a candidate that is not an image array", InputError,
                 lambda: list(select_frames([("000000.png", "cam0", np.zeros(5, np.uint8))], FrameConfig())),
                 "000000.png", "is not an image")


# ------------------------------------------------------------------------------------------------------- CAD


def test_cad_missing_and_empty(tmp_path: Path) -> None:
    expect_error("cad", "missing CAD file", InputError, lambda: load_cad(tmp_path / "valve.ply"),
                 "CAD file not found", "valve.ply")
    (tmp_path / "valve.ply").write_bytes(b"")
    expect_error("cad", "empty CAD file (0 bytes)", InputError, lambda: load_cad(tmp_path / "valve.ply"),
                 "valve.ply", "is empty (0 bytes)", "re-export")


def test_step_without_solids(tmp_path: Path) -> None:
    """A STEP holding only a wire (curves, no surface): named, with the fix."""
    from OCP.BRepBuilderAPI import BRepBuilderAPI_MakeEdge
    from OCP.gp import gp_Pnt
    from step_testdata import write_step

    edge = BRepBuilderAPI_MakeEdge(gp_Pnt(0, 0, 0), gp_Pnt(100, 0, 0)).Edge()
    path = write_step(tmp_path / "sketch.step", {"centreline": edge}, "mm")
    expect_error("cad", "STEP with no solids (only a curve)", InputError, lambda: load_cad(path),
                 "sketch.step", "holds no solid or surface", "export the bodies as solids")


def test_step_garbage_text(tmp_path: Path) -> None:
    path = tmp_path / "panel.step"
    path.write_text("ISO-10303-21;\nHEADER;\nthis is not STEP\n")
    expect_error("cad", "STEP file that does not parse", InputError, lambda: load_cad(path), "panel.step",
                 "re-export")


def test_step_in_inches_loads_in_metres_and_records_inch(tmp_path: Path) -> None:
    """Not an error: a STEP declaring inches is scaled to metres and its model says 'in'."""
    from step_testdata import box, write_step

    path = write_step(tmp_path / "plate.step", {"plate": box((1.0, 0.5, 0.1))}, "in")
    assert "CONVERSION_BASED_UNIT('INCH'" in path.read_text()
    model = load_cad(path)
    assert model.unit == "in" and np.allclose(model.extent, [1.0, 0.5, 0.1], atol=1e-5)


@pytest.mark.parametrize("ext", ["ply", "dae", "glb", "obj"])
def test_cad_garbage_bytes(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"valve.{ext}"
    path.write_bytes(np.random.default_rng(1).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    msg = expect_error("cad", f"garbage bytes as .{ext}", InputError, lambda: load_cad(path), str(path))
    assert "cannot read CAD file" in msg or "no triangle faces" in msg


def test_cad_unsupported_extension(tmp_path: Path) -> None:
    (tmp_path / "valve.sldprt").write_text("native CAD")
    expect_error("cad", "unsupported format (.sldprt)", InputError, lambda: load_cad(tmp_path / "valve.sldprt"),
                 "unsupported extension '.sldprt'", "as STEP", "convert it")


def test_cad_in_millimetres_is_detected_and_a_wrong_unit_refused(tmp_path: Path, caplog) -> None:
    trimesh.creation.box(extents=(600.0, 400.0, 300.0)).export(tmp_path / "valve_mm.ply")
    model = expect_warning("cad", "CAD in mm, unit not given (600 mm valve)", caplog,
                           lambda: load_cad(tmp_path / "valve_mm.ply"), "valve_mm.ply", "assuming millimetres")
    assert model.unit == "mm" and np.allclose(model.extent, [0.6, 0.4, 0.3])
    as_metres = load_cad(tmp_path / "valve_mm.ply", unit="m", class_name="valve")
    expect_error("cad", "CAD in mm loaded with unit='m', checked against a valve's size", UnitError,
                 lambda: check_unit(as_metres, (0.1, 2.0)), "600 m across", "Pass unit='mm'")


def test_cad_too_big_in_any_unit(tmp_path: Path) -> None:
    trimesh.creation.box(extents=(2e5, 1.0, 1.0)).export(tmp_path / "huge.ply")
    expect_error("cad", "CAD 200 km across in file units", UnitError, lambda: load_cad(tmp_path / "huge.ply"),
                 "huge.ply", "even if in millimetres", "pass unit=")


def test_cad_non_manifold_warns(tmp_path: Path, caplog) -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1.0]]) * 0.5
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # three faces on edge 0-1
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "fin.ply")
    model = expect_warning("cad", "non-manifold mesh (3 faces on one edge)", caplog,
                           lambda: load_cad(tmp_path / "fin.ply", unit="m"), "fin.ply", "1 non-manifold edges",
                           "Repair")
    assert len(model.faces) == 3


def test_cad_all_faces_degenerate(tmp_path: Path) -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0.0]])
    trimesh.Trimesh(v, np.array([[0, 1, 2], [1, 2, 3]]), process=False).export(tmp_path / "line.ply")
    expect_error("cad", "every face has zero area", InputError, lambda: load_cad(tmp_path / "line.ply", unit="m"),
                 "line.ply", "all 2 faces are degenerate")


def test_cad_non_finite_vertices(tmp_path: Path) -> None:
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    expect_error("cad", "NaN vertex coordinates (OBJ)", InputError, lambda: load_cad(tmp_path / "nan.obj"),
                 "nan.obj", "non-finite")


# ------------------------------------------------------------------------------------------------ scene spec


def _scene(tmp_path: Path, old: str = "", new: str = "", *, append: str = "") -> Path:
    path = write_tiny_scene(tmp_path / "scene.toml", effects=[], frames=4)
    text = path.read_text()
    if old:
        assert old in text
        text = text.replace(old, new, 1)
    path.write_text(text + append)
    return path


def test_scene_is_valid_unchanged(tmp_path: Path) -> None:
    assert load_scene(_scene(tmp_path)).camera.width == 160


@pytest.mark.parametrize(
    ("what", "old", "new", "fragments"),
    [
        ("misspelled top-level table [trajectroy]", "[trajectory]", "[trajectroy]",
         ["unknown key 'trajectroy'", "did you mean 'trajectory'"]),
        ("misspelled key camera.widht", "width = 160", "widht = 160",
         ["unknown key 'camera.widht'", "did you mean 'camera.width'"]),
        ("zero resolution", "width = 160", "width = 0", ["'camera.width' = 0 is out of range", ">= 8"]),
        ("negative resolution", "height = 120", "height = -120", ["'camera.height' = -120 is out of range"]),
        ("field of view 180 deg", "hfov_deg = 65.0", "hfov_deg = 180.0", ["'camera.hfov_deg' = 180.0", "< 179"]),
        ("negative attenuation", 'jerlov = "II"', "beta_D = [0.1, -0.2, 0.1]\nbeta_B = [0.1, 0.1, 0.1]\n"
         "B_inf = [0.1, 0.1, 0.1]", ["'water.beta_D[1]' = -0.2 is out of range", ">= 0"]),
        ("veiling light above 1", 'jerlov = "II"', "beta_D = [0.1, 0.2, 0.1]\nbeta_B = [0.1, 0.1, 0.1]\n"
         "B_inf = [0.1, 3.0, 0.1]", ["'water.B_inf[1]' = 3.0 is out of range", "<= 1"]),
        ("only beta_D given", 'jerlov = "II"', "beta_D = [0.1, 0.2, 0.1]", ["give all of beta_D, beta_B and B_inf"]),
        ("unknown Jerlov type", 'jerlov = "II"', 'jerlov = "IV"', ["'water.jerlov' = 'IV' is not allowed", "'IB'"]),
        ("NaN orbit radius", "radius_m = 3.2", "radius_m = nan", ["'trajectory.radius_m' = nan is not a finite"]),
        ("inf object position", "position = [0.0, 0.0, 0.3]", "position = [inf, 0.0, 0.3]",
         ["'objects[0].position[0]' = inf is not a finite number"]),
        ("zero frames", "frames = 4", "frames = 0", ["'trajectory.frames' = 0 is out of range"]),
        ("string where a number is expected", "fps = 1.0", 'fps = "fast"',
         ["'trajectory.fps' = 'fast' has the wrong type", "a number"]),
        ("unknown effect", "effects = []", 'effects = ["fog"]', ["unknown effect(s) ['fog']", "marine_snow"]),
        ("unknown procedural part", 'source = "procedural:box"', 'source = "procedural:boxx"',
         ["unknown procedural part 'boxx'", "procedural:box"]),
        ("object class not in classes", 'class_name = "valve"', 'class_name = "pump"',
         ["object 'valve' has class 'pump'"]),
        ("camera inside an object", "radius_m = 3.2\nheight_m = 1.6", "radius_m = 0.3\nheight_m = 0.6",
         ["the camera of frame 0", "is inside object 'block'", "change the trajectory"]),
        ("camera under the seabed", "height_m = 1.6", "height_m = -0.5",
         ["the camera of frame 0 is under the seabed", "raise trajectory.height_m"]),
        ("TOML syntax error", "width = 160", "width = = 160", ["could not parse"]),
    ],
)
def test_scene_spec_errors(tmp_path: Path, what: str, old: str, new: str, fragments: list[str]) -> None:
    path = _scene(tmp_path, old, new)
    expect_error("scene spec", what, ConfigError, lambda: load_scene(path), str(path), *fragments)


def test_scene_spec_not_utf8_and_missing(tmp_path: Path) -> None:
    path = tmp_path / "scene.toml"
    path.write_bytes(b'name = "caf\xe9"\n')
    expect_error("scene spec", "scene file not UTF-8 (latin-1 byte)", ConfigError, lambda: load_scene(path),
                 str(path), "not a UTF-8 text file", "save it as UTF-8")
    expect_error("scene spec", "missing scene file", ConfigError, lambda: load_scene(tmp_path / "nope.toml"),
                 "config file not found", "nope.toml")


def test_scene_mesh_source_missing(tmp_path: Path) -> None:
    scene = tmp_path / "scene.toml"
    expect_error("scene spec", "object mesh file that does not exist", InputError,
                 lambda: resolve_source("meshes/pump.ply", scene), "mesh not found for source 'meshes/pump.ply'",
                 "relative to the scene file")


# --------------------------------------------------------------------------------------------------- BOP scene


@pytest.fixture
def bop_copy(tiny_bop: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "000000"
    shutil.copytree(tiny_bop, dst)
    return dst


def _edit_json(path: Path, fn) -> None:
    data = json.loads(path.read_text())
    fn(data)
    path.write_text(json.dumps(data))


def test_bop_reads_unchanged(bop_copy: Path) -> None:
    scene = BopScene(bop_copy)
    assert scene.ids == [0, 1] and scene.depth_m(0).shape == (120, 160)
    assert scene.mask(1, 0).shape == (120, 160) and scene.rgb(0).shape == (120, 160, 3)


def test_bop_missing_json(bop_copy: Path) -> None:
    (bop_copy / "scene_gt.json").unlink()
    expect_error("bop", "scene_gt.json missing", InputError, lambda: BopScene(bop_copy), "is not a BOP scene",
                 "scene_gt.json is missing")


def test_bop_mismatched_ids(bop_copy: Path) -> None:
    _edit_json(bop_copy / "scene_camera.json", lambda d: d.update({"7": d["0"]}))
    expect_error("bop", "image id 7 only in scene_camera.json", InputError, lambda: BopScene(bop_copy),
                 "image ids ['7'] are in only one of scene_camera.json/scene_gt.json")


def test_bop_info_does_not_match_gt(bop_copy: Path) -> None:
    _edit_json(bop_copy / "scene_gt_info.json", lambda d: d["1"].pop())
    expect_error("bop", "scene_gt_info.json with fewer instances than scene_gt.json", InputError,
                 lambda: BopScene(bop_copy), "scene_gt_info.json, image 1", "scene_gt.json has")


@pytest.mark.parametrize(
    ("what", "file", "edit", "fragments"),
    [
        ("cam_K with 8 numbers", "scene_camera.json", lambda d: d["0"]["cam_K"].pop(),
         ["image 0", "'cam_K' must be a list of 9 finite numbers"]),
        ("cam_K missing", "scene_camera.json", lambda d: d["1"].pop("cam_K"), ["image 1", "'cam_K'"]),
        ("negative depth_scale", "scene_camera.json", lambda d: d["0"].update(depth_scale=-1),
         ["'depth_scale' must be a positive number"]),
        ("obj_id 0", "scene_gt.json", lambda d: d["0"][0].update(obj_id=0),
         ["image 0, instance 0", "'obj_id' must be a positive integer"]),
        ("R that is not a rotation", "scene_gt.json", lambda d: d["1"][0].update(cam_R_m2c=[2, 0, 0, 0, 1, 0, 0, 0, 1]),
         ["image 1, instance 0", "'cam_R_m2c' is not a rotation matrix"]),
        ("string image id", "scene_gt.json", lambda d: d.update({"first": []}), ["key 'first' is not an image id"]),
        ("list instead of an object", "scene_camera.json", lambda d: d.update({"0": [1, 2]}),
         ["the entry of image 0 must be a JSON object"]),
    ],
)
def test_bop_bad_json_entries(bop_copy: Path, what: str, file: str, edit, fragments: list[str]) -> None:
    _edit_json(bop_copy / file, edit)
    expect_error("bop", what, InputError, lambda: BopScene(bop_copy), file, *fragments)


def test_bop_json_not_json(bop_copy: Path) -> None:
    (bop_copy / "scene_gt.json").write_text('{"0": [')
    expect_error("bop", "truncated scene_gt.json", InputError, lambda: BopScene(bop_copy),
                 "scene_gt.json is not valid JSON", "re-run the stage")


def test_bop_image_files(bop_copy: Path) -> None:
    scene = BopScene(bop_copy)
    (bop_copy / "depth" / "000001.png").unlink()
    expect_error("bop", "depth PNG missing", InputError, lambda: scene.depth_m(1), "depth/000001.png is missing",
                 "image 1 is listed in scene_camera.json")
    (bop_copy / "depth" / "000000.png").write_bytes(b"not a png")
    expect_error("bop", "depth PNG corrupt", InputError, lambda: scene.depth_m(0), "depth/000000.png",
                 "could not decode image")
    write_image(bop_copy / "depth" / "000000.png", np.ones((60, 80), np.uint16))
    expect_error("bop", "depth PNG of the wrong size", InputError, lambda: scene.depth_m(0), "is 80x60",
                 "says image 0 is 160x120")
    write_image(bop_copy / "depth" / "000000.png", np.ones((120, 160), np.uint8))
    expect_error("bop", "8-bit depth PNG", InputError, lambda: scene.depth_m(0),
                 "must be a single-channel 16-bit PNG", "uint8")
    (bop_copy / "mask_visib" / "000000_000000.png").unlink()
    expect_error("bop", "mask PNG missing", InputError, lambda: scene.mask(0, 0), "mask_visib/000000_000000.png")


# ------------------------------------------------------------------------------------------- configs and types


def test_stage_config_misspelled_key(tmp_path: Path) -> None:
    path = tmp_path / "sfm.toml"
    path.write_text("[frames]\nblur_ratoi = 0.2\n")
    expect_error("config", "misspelled key in an SfM config file", ConfigError,
                 lambda: resolve(SfMConfig, SFM_PRESETS, "fast", path), str(path), "unknown key 'frames.blur_ratoi'",
                 "did you mean 'frames.blur_ratio'")


def test_config_file_errors(tmp_path: Path) -> None:
    path = tmp_path / "sfm.yaml"
    path.write_text("- just\n- a list\n")
    expect_error("config", "YAML whose top level is a list", ConfigError, lambda: read_mapping(path),
                 "top level must be a table/mapping")
    path = tmp_path / "sfm.json"
    path.write_text("[" * 100000)
    expect_error("config", "JSON nested 100000 deep", ConfigError, lambda: read_mapping(path), "could not parse")
    path = tmp_path / "sfm.toml"
    path.write_text("[frames]\nfps = 1e400\n")
    expect_error("config", "float overflowing to inf", ConfigError, lambda: resolve(SfMConfig, path=path),
                 "'frames.fps' = inf is not a finite number")


def test_transforms_and_cameras_refuse_nonsense() -> None:
    expect_error("types", "Sim3 with scale 0", DegenerateGeometryError, lambda: Sim3(0.0),
                 "scale must be finite and > 0")
    expect_error("types", "Rigid3 with a NaN translation", InputError, lambda: Rigid3(np.eye(3), [0, np.nan, 0]),
                 "Rigid3.t must be finite")
    expect_error("types", "Rigid3 from a 3x3 matrix", InputError, lambda: Rigid3.from_matrix(np.eye(3)),
                 "expects a (4, 4) homogeneous matrix")
    expect_error("types", "Camera with width 0", InputError, lambda: Camera(np.eye(3), 0, 10),
                 "image size must be positive")
    with pytest.raises(ValueError):  # the project's errors stay ValueErrors for callers that catch those
        Sim3(-1.0)

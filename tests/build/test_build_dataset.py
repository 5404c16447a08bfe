"""``cadalign build-dataset`` end to end on a tiny simulated capture, checked against the simulator's truth.

The coarse alignment uses picks (the thesis aligned by hand): four CAD points and where they are in the
SfM frame, perturbed by 2 cm, so this test checks the builder (SfM cameras -> metric poses -> ray-cast
depth, masks, poses -> BOP) independently of the global registration, which tests/align covers.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from cadalign.errors import AlignmentError
from cadalign.formats.bop import BopScene
from cadalign.io import read_image, read_json
from cadalign.testing.tiny_scene import write_build_capture, write_picks_from_truth


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> tuple[Path, Path]:
    """(scene spec, simulator output) of a 12-frame 320x240 orbit with light water effects."""
    from cadalign.sim.run import simulate

    root = tmp_path_factory.mktemp("capture")
    spec = write_build_capture(root / "tiny.toml", effects=["attenuation", "backscatter"], frames=12)
    return spec, simulate(spec, root / "sim", video=False, contact_sheet=False)


@pytest.fixture(scope="module")
def built(capture: tuple[Path, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    from cadalign.build.run import build_dataset
    from cadalign.sfm import PRESETS, run

    spec, sim = capture
    out = tmp_path_factory.mktemp("build")
    sfm_dir = run(PRESETS["fast"], sim / "frames", out / "sfm")  # build_dataset reuses this
    write_picks_from_truth(sfm_dir, sim, out / "picks.json")
    return build_dataset(sim / "frames", spec, out, preset="fast", picks=out / "picks.json", gt=sim)


def test_dataset_matches_the_truth(built: Path) -> None:
    """Bounds for this tiny capture (12 frames, 320x240, ~1000 SfM points, a 2 m block): the SfM alone
    limits them to about 1 % in scale. They are looser than the issue's numbers for the 640x480 default
    scene (0.3 deg, 2 cm, 0.5 %), which the build benchmark measures, but catch any convention error
    (a flipped pose, a mm/m slip, a half-pixel shift shows up as metres, degrees or IoU far below these)."""
    report = read_json(built / "build_report.json")
    assert report["frames_verified"] == report["frames"] and not report["frames_not_verified"]
    vt = report["vs_truth"]
    a = vt["alignment"]
    assert a["rotation_deg"] <= 0.6 and a["translation_m"] <= 0.03 and a["scale_rel"] <= 0.015, a
    assert vt["depth"]["cad_depth"]["abs_rel"] <= 0.015, vt["depth"]
    # the block stands on the seabed: SfM finds the floor, and the cameras were aligned to the contours
    assert report["seabed"]["found"] and abs(report["seabed"]["cad_lowest_above_m"]) < 0.05, report["seabed"]
    assert report["edge_alignment"]["shared"]["applied"], report["edge_alignment"]
    assert vt["mask_visib_iou"]["all"]["median"] >= 0.9, vt["mask_visib_iou"]
    assert vt["pose_in_camera"]["rotation_deg"]["median"] <= 0.5
    assert vt["pose_in_camera"]["translation_m"]["median"] <= 0.03
    # the thesis's comparison: CAD depth is dense, SfM depth is sparse
    assert vt["depth"]["cad_depth"]["coverage"] > 0.9 > 0.2 > vt["depth"]["sfm_depth"]["coverage"]
    html = (built / "build_report.html").read_text()
    assert "CAD depth vs SfM depth" in html
    # issue 44: the alignment was verified against the images and the report shows the evidence
    assert report["verification"]["outcome"] == "ok" and report["verification"]["hypotheses"][0]["edge"] > 0.5
    assert "Verification against the images" in html and (built / "verify" / "hypotheses.png").is_file()


def test_dataset_layout_splits_and_coco(built: Path) -> None:
    ds = built / "dataset"
    scene = BopScene(ds / "all" / "000000")
    assert len(scene.ids) >= 10
    info = read_json(ds / "models" / "models_info.json")
    assert len(info) == 3
    splits = read_json(ds / "splits.json")
    ids = splits["train"] + splits["val"] + splits["test"]
    assert len(ids) == len(set(ids)) and set(ids) <= set(scene.ids) and splits["train"]
    coco = read_json(ds / "coco_train.json")
    assert {im["id"] for im in coco["images"]} == set(splits["train"]) and coco["annotations"]
    depth_sfm = read_image(ds / "all" / "000000" / "depth_sfm" / "000000.png", unchanged=True)
    assert depth_sfm.dtype == np.uint16 and 0 < (depth_sfm > 0).mean() < 0.2
    # the images are SfM's CLAHE-enhanced frames, and the dataset says so (for 'cadalign infer' on raw video)
    from cadalign.sfm.image_prep import read_prep

    assert read_json(ds / "images.json")["enhance"] == "clahe"
    assert read_prep(ds / "all" / "000000") == {"enhance": "clahe", "clahe_clip": 2.0, "clahe_tiles": 8}


def test_interrupted_render_resumes_to_the_same_result(built: Path, capture: tuple[Path, Path]) -> None:
    """Deleting the last frames' records (as a kill mid-render leaves it) and re-running redoes only those
    frames, reuses SfM and the alignment, and gives identical files."""
    from cadalign.build.run import build_dataset

    spec, sim = capture
    scene_dir = built / "dataset" / "all" / "000000"
    before = {p.name: p.read_bytes() for p in sorted((scene_dir / "depth").glob("*.png"))}
    gt_before = read_json(scene_dir / "scene_gt.json")
    for p in sorted((scene_dir / "frames_json").glob("*.json"))[-3:]:
        p.unlink()
    (scene_dir / "depth" / sorted(before)[-1]).write_bytes(b"torn")
    sfm_mtime = (built / "sfm" / "sparse" / "0" / "points3D.bin").stat().st_mtime_ns
    build_dataset(sim / "frames", spec, built, preset="fast", picks=built / "picks.json", gt=sim)
    assert (built / "sfm" / "sparse" / "0" / "points3D.bin").stat().st_mtime_ns == sfm_mtime
    after = {p.name: p.read_bytes() for p in sorted((scene_dir / "depth").glob("*.png"))}
    assert after == before
    assert read_json(scene_dir / "scene_gt.json") == gt_before


def test_cad_in_the_wrong_unit_fails_the_gate(capture: tuple[Path, Path], built: Path, tmp_path: Path,
                                              shared_data: Path) -> None:
    """The hot stab read as millimetres (it is in metres) gives an alignment error naming the unit, no dataset."""
    from cadalign.build.run import build_dataset

    _, sim = capture
    out = tmp_path / "bad"
    shutil.copytree(built / "sfm", out / "sfm")
    hot_stab = shared_data / "uuv_subsea_cad" / "hot_stab" / "meshes" / "HotStab.dae"
    with pytest.raises(AlignmentError, match="(?i)unit"):
        build_dataset(sim / "frames", hot_stab, out, preset="fast", cad_unit="mm")
    assert not (out / "dataset").exists()


@pytest.mark.parametrize(("ros", "kw"), [(1, {}), (2, {"storage": "mcap", "compressed": True})],
                         ids=["ros1-raw", "ros2-mcap-png"])
def test_a_bag_builds_the_same_dataset_as_the_frames_folder(built: Path, capture: tuple[Path, Path],
                                                             tmp_path: Path, ros: int, kw: dict) -> None:
    """The capture's frames recorded as a ROS 1 bag (raw rgb8) or a ROS 2 bag (mcap, png CompressedImage) on
    /camera/image_raw give the folder's dataset: the same frames, poses within 5 mm / 0.3 deg and depth within
    5 mm. Both builds map with one thread (SfM with two is not repeatable: on this 12-frame capture a rerun
    once failed the fitness gate)."""
    from bag_testdata import write_bag

    from cadalign.build.run import build_dataset

    spec, sim = capture
    frames = [read_image(p) for p in sorted((sim / "frames").glob("*.png"))]
    bag = write_bag(frames, tmp_path / ("dive.bag" if ros == 1 else "dive"), ros=ros, **kw)
    one = {"num_threads": 1}
    folder = build_dataset(sim / "frames", spec, tmp_path / "folder", preset="fast", picks=built / "picks.json",
                           sfm_set=one)
    out = build_dataset(bag, spec, tmp_path / "out", preset="fast", picks=built / "picks.json",
                        topic="/camera/image_raw", sfm_set=one)
    ref, got = folder / "dataset" / "all" / "000000", out / "dataset" / "all" / "000000"
    _assert_poses_close(read_json(got / "scene_gt.json"), read_json(ref / "scene_gt.json"))
    names = sorted(p.name for p in (ref / "depth").glob("*.png"))
    assert sorted(p.name for p in (got / "depth").glob("*.png")) == names
    d_got = read_image(got / "depth" / "000000.png", unchanged=True).astype(float)
    d_ref = read_image(ref / "depth" / "000000.png", unchanged=True).astype(float)
    assert np.median(np.abs(d_got - d_ref)[d_ref > 0]) <= 5.0  # mm (depth_scale 1)
    stamps = [f["stamp_ns"] for f in read_json(out / "sfm" / "frames.json")["frames"]]
    assert stamps == sorted(stamps) and None not in stamps


def _assert_poses_close(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for k in a:
        for x, y in zip(a[k], b[k], strict=True):
            assert x["obj_id"] == y["obj_id"]
            assert np.allclose(x["cam_t_m2c"], y["cam_t_m2c"], atol=5.0)  # mm; multi-threaded SfM: ~1 mm apart
            assert np.allclose(x["cam_R_m2c"], y["cam_R_m2c"], atol=5e-3)  # ~0.3 deg


def test_a_wrong_global_alignment_is_refused_by_the_images(capture: tuple[Path, Path], built: Path,
                                                          tmp_path: Path) -> None:
    """Issue 44: on this 12-frame capture the global registration finds no right candidate (all are 90-180 deg
    off) and its best one passes every cloud gate. The image verification refuses it: no dataset, the reason
    (edges and free space), the fix, the picture of the hypotheses and a report; a person's choice of a
    hypothesis is refused too, as the images contradict it."""
    from cadalign.align.verify.run import VerificationError
    from cadalign.build.run import build_dataset

    spec, sim = capture
    out = tmp_path / "global"
    shutil.copytree(built / "sfm", out / "sfm")
    with pytest.raises(VerificationError) as exc:
        build_dataset(sim / "frames", spec, out, preset="fast")
    msg = str(exc.value)
    assert exc.value.verification.outcome in ("wrong", "uncertain") and "FAIL" in msg and "--hypothesis" in msg
    assert not (out / "dataset").exists()
    assert (out / "verify" / "hypotheses.png").stat().st_size > 1000
    report = read_json(out / "build_report.json")
    assert report["verification"]["outcome"] == exc.value.verification.outcome
    assert "Refused" in (out / "build_report.html").read_text()
    with pytest.raises(VerificationError):
        build_dataset(sim / "frames", spec, out, preset="fast", hypothesis=1)
    assert not (out / "dataset").exists()

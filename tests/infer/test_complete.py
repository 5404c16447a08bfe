"""Track completion (cadalign.infer.complete): visibility from depth, the completion pass, and ``infer`` end to end
with a detector that misses a part in one frame."""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import imageio.v2 as iio
import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from cadalign.cad.model import CadModel
from cadalign.cli.main import app
from cadalign.infer.complete import TrackCompleter, WorldTrack, project_visible
from cadalign.infer.config import CompleteConfig
from cadalign.infer.model_geom import ModelGeometry, render_depth
from cadalign.metrics.pose_eval import CroppedMask
from cadalign.types import Rigid3

K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
SHAPE = (120, 160)


@pytest.fixture(scope="module")
def cube() -> ModelGeometry:
    m = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    return ModelGeometry.from_cad(CadModel("cube", np.asarray(m.vertices), np.asarray(m.faces)), 500)


def _at(z: float, x: float = 0.0) -> Rigid3:
    return Rigid3(np.eye(3), np.array([x, 0.0, z]))


def _far() -> np.ndarray:
    return np.full(SHAPE, 50.0)


def test_an_unoccluded_part_is_seen_whole(cube: ModelGeometry) -> None:
    p = project_visible(cube, _at(4.0), K, _far(), CompleteConfig())
    sil = np.isfinite(render_depth(cube, _at(4.0), K, SHAPE))
    rows, cols = np.flatnonzero(sil.any(1)), np.flatnonzero(sil.any(0))
    assert p is not None
    np.testing.assert_array_equal(p.box_xyxy, [cols[0], rows[0], cols[-1] + 1, rows[-1] + 1])
    np.testing.assert_array_equal(p.mask.full(SHAPE), sil)
    assert np.array_equal(p.T_cam_from_obj.matrix(), _at(4.0).matrix())


def test_occlusion_hides_and_crops_the_part(cube: ModelGeometry) -> None:
    cfg = CompleteConfig(min_visible=0.3)
    wall = np.full(SHAPE, 2.0)  # a wall in front of the whole part
    assert project_visible(cube, _at(4.0), K, wall, cfg) is None
    half = _far()
    half[:, :80] = 2.0  # the left half of the image is behind a nearer surface
    p = project_visible(cube, _at(4.0), K, half, cfg)
    assert p is not None and p.box_xyxy[0] == 80
    full = project_visible(cube, _at(4.0), K, _far(), cfg)
    assert p.box_xyxy[2] == full.box_xyxy[2]
    # the part seen through its own surface: observed depth 1 cm short of the model, within the tolerance
    z = render_depth(cube, _at(4.0), K, SHAPE)
    surface = np.where(np.isfinite(z), z - 0.01, 50.0)
    assert project_visible(cube, _at(4.0), K, surface, cfg) is not None
    assert project_visible(cube, _at(4.0), K, surface, replace(cfg, depth_tol_m=0.0)) is None
    # a relative tolerance lets a depth 5 % short pass
    short = np.where(np.isfinite(z), z * 0.95, 50.0)
    assert project_visible(cube, _at(4.0), K, short, cfg) is None
    assert project_visible(cube, _at(4.0), K, short, replace(cfg, depth_tol_rel=0.1)) is not None
    # needing more of the part in sight than half
    assert project_visible(cube, _at(4.0), K, half, replace(cfg, min_visible=0.9)) is None


@pytest.mark.parametrize("bad", [np.nan, 0.0, -1.0, np.inf])
def test_no_valid_depth_shows_nothing(cube: ModelGeometry, bad: float) -> None:
    assert project_visible(cube, _at(4.0), K, np.full(SHAPE, bad), CompleteConfig()) is None


@pytest.mark.parametrize("T", [_at(-4.0), _at(0.1), _at(4.0, x=20.0)])
def test_behind_at_or_beside_the_camera_is_not_in_view(cube: ModelGeometry, T: Rigid3) -> None:
    assert project_visible(cube, T, K, _far(), CompleteConfig()) is None


@dataclass(frozen=True)
class _Rec:
    frame: int
    frame_name: str
    track_id: int
    label: int
    score: float
    box_xyxy: np.ndarray
    T_cam_from_obj: Rigid3
    T_detector: Rigid3 = field(default_factory=Rigid3.identity)
    T_refined: Rigid3 = field(default_factory=Rigid3.identity)
    class_name: str = "valve"
    refine_iters: dict = field(default_factory=dict)
    mask: object = None
    source: str = "detector"
    box_detector: object = None
    obj_id: int = 7  # the CAD model of the tests' tracks


def _cams(n: int) -> list[Rigid3]:
    """``T_world_from_cam`` of a camera sliding along x (the part, at the world origin, drifts left in the image)."""
    return [Rigid3(np.eye(3), np.array([0.1 * i, 0.0, -4.0])) for i in range(n)]


def _video(cube: ModelGeometry, seen: dict[int, list[int]], shift_px: float = 0.0) -> tuple[list[_Rec], list[Rigid3]]:
    """Records of tracks (id -> frames detected) of parts at x = 0 (track 0) and x = 1 m (others), boxes exact
    (plus ``shift_px``)."""
    cams, recs = _cams(5), []
    for tid, frames in seen.items():
        T_wo = _at(0.0, x=0.0 if tid == 0 else 1.0)
        for f in frames:
            T = cams[f].inverse() @ T_wo
            p = project_visible(cube, T, K, _far(), CompleteConfig())
            recs.append(_Rec(f, f"{f:06d}.png", tid, 2, 0.5 + 0.1 * f, p.box_xyxy + shift_px, T))
    return recs, cams


def _complete(cube, recs, cams, tracks, cfg=None, depth=None):
    c = TrackCompleter(cfg or CompleteConfig(), tracks, recs, lambda oid: cube)
    for i, T in enumerate(cams):
        c.frame(i, f"{i:06d}.png", K, T, _far() if depth is None else depth)
    return c.result()


def test_a_missed_frame_is_completed_with_the_world_pose(cube: ModelGeometry) -> None:
    recs, cams = _video(cube, {0: [0, 1, 3, 4]})
    T_wo = _at(0.0)
    out, summary = _complete(cube, recs, cams, [WorldTrack(0, 2, 7, T_wo)])
    added = [r for r in out if r.source == "track"]
    assert len(added) == 1 and added[0].frame == 2 and added[0].frame_name == "000002.png"
    T = cams[2].inverse() @ T_wo
    assert np.allclose(added[0].T_cam_from_obj.t, T.t) and np.allclose(added[0].T_cam_from_obj.R, T.R)
    assert added[0].score == pytest.approx(np.median([0.5, 0.6, 0.8, 0.9]))
    assert isinstance(added[0].mask, CroppedMask) and added[0].refine_iters == {}
    assert [r.frame for r in out] == [0, 1, 2, 3, 4]
    assert summary == {"tracks": 1, "untrusted": 0, "duplicates": 0, "added": {"valve": 1}, "dropped": 0}
    assert {r.obj_id for r in out} == {7}  # the track's model (the refit's choice), on its own detections too


def test_a_track_whose_model_changed_reports_it_with_the_world_pose(cube: ModelGeometry) -> None:
    # the refit chose model 8 for track 0, whose detections were refined with model 7: without ``smooth`` they
    # still take the world pose (their own poses are of the other model)
    recs, cams = _video(cube, {0: [0, 1, 3, 4]})
    recs = [replace(r, obj_id=7, T_cam_from_obj=Rigid3(np.eye(3), r.T_cam_from_obj.t + 1.0)) for r in recs]
    T_wo = _at(0.0)
    out, _ = _complete(cube, recs, cams, [WorldTrack(0, 2, 8, T_wo)], CompleteConfig(smooth=False))
    assert {r.obj_id for r in out} == {8}
    for r in out:
        assert np.allclose(r.T_cam_from_obj.t, (cams[r.frame].inverse() @ T_wo).t)
    same, _ = _complete(cube, recs, cams, [WorldTrack(0, 2, 7, T_wo)], CompleteConfig(smooth=False))
    assert all(np.allclose(a.T_cam_from_obj.t, b.T_cam_from_obj.t) for a, b in zip(recs, same[:2] + same[3:],
                                                                                  strict=True))


def test_short_tracks_are_dropped_and_not_completed(cube: ModelGeometry) -> None:
    recs, cams = _video(cube, {0: [0, 1, 2, 3], 1: [4]})
    tracks = [WorldTrack(0, 2, 7, _at(0.0)), WorldTrack(1, 2, 7, _at(0.0, x=1.0))]
    out, summary = _complete(cube, recs, cams, tracks)
    assert {r.track_id for r in out} == {0} and summary["dropped"] == 1
    assert [r.frame for r in out if r.source == "track"] == [4]
    kept, _ = _complete(cube, recs, cams, tracks, CompleteConfig(drop_short=False))
    assert sum(r.track_id == 1 for r in kept) == 1
    # records not fused into tracks (temporal mode none: track id -1) are never short
    unfused = [replace(r, track_id=-1) for r in recs[:2]]
    out, summary = _complete(cube, unfused, cams, [])
    assert len(out) == 2 and summary["dropped"] == 0


def test_a_duplicate_of_a_completed_track_is_dropped(cube: ModelGeometry) -> None:
    # track 1 marked as the same part as track 0 (cadalign.infer.refine.track_fit.duplicates): its detections go, and it
    # is not completed, as long as track 0 is completed
    recs, cams = _video(cube, {0: [0, 1, 3, 4], 1: [0, 1, 2]})
    tracks = [WorldTrack(0, 2, 7, _at(0.0)), WorldTrack(1, 2, 7, _at(0.0, x=1.0), duplicate_of=0)]
    out, summary = _complete(cube, recs, cams, tracks)
    assert {r.track_id for r in out} == {0} and summary["duplicates"] == 1 and summary["dropped"] == 3
    assert summary["untrusted"] == 0 and [r.frame for r in out if r.source == "track"] == [2]
    # the keeper too short to be completed: the duplicate stays, and is completed itself
    recs, cams = _video(cube, {0: [0, 1], 1: [0, 1, 2]})
    out, summary = _complete(cube, recs, cams, tracks)
    assert {r.track_id for r in out} == {1} and summary["duplicates"] == 0
    assert [r.frame for r in out if r.source == "track"] == [3, 4]


def test_a_track_its_detections_disagree_with_is_not_completed(cube: ModelGeometry) -> None:
    recs, cams = _video(cube, {0: [0, 1, 3, 4]}, shift_px=30.0)  # every detection far from the projection
    out, summary = _complete(cube, recs, cams, [WorldTrack(0, 2, 7, _at(0.0))])
    assert summary["untrusted"] == 1 and all(r.source == "detector" for r in out)
    out, _ = _complete(cube, recs, cams, [WorldTrack(0, 2, 7, _at(0.0))], CompleteConfig(consistency_iou=0.0))
    assert sum(r.source == "track" for r in out) == 1


def test_drop_untrusted_drops_only_the_detections_of_untrusted_tracks(cube: ModelGeometry) -> None:
    # track 0 agrees with its projection, track 1's detections are far from it: with drop_untrusted only track 1's
    # detections go; a track no frame could check (no camera pose / depth) and a short one are left to the other rules
    recs0, cams = _video(cube, {0: [0, 1, 3, 4]})
    recs1, _ = _video(cube, {1: [0, 1, 2]}, shift_px=30.0)
    tracks = [WorldTrack(0, 2, 7, _at(0.0)), WorldTrack(1, 2, 7, _at(0.0, x=1.0))]
    out, summary = _complete(cube, recs0 + recs1, cams, tracks)
    assert summary["untrusted"] == 1 and sum(r.track_id == 1 for r in out) == 3
    out, summary = _complete(cube, recs0 + recs1, cams, tracks, CompleteConfig(drop_untrusted=True))
    assert {r.track_id for r in out} == {0} and summary["dropped"] == 3
    assert [r.frame for r in out if r.source == "track"] == [2]
    # nothing checked (no frame fed): nothing dropped
    c = TrackCompleter(CompleteConfig(drop_untrusted=True), tracks, recs0 + recs1, lambda oid: cube)
    out, _ = c.result()
    assert len(out) == len(recs0) + len(recs1)


def test_a_track_its_model_does_not_fit_is_not_trusted(cube: ModelGeometry) -> None:
    # a consistent track whose refitted model explains its depth poorly (fit_rel 0.6) is not completed under
    # max_fit_rel = 0.55, and with drop_untrusted its detections go; one that was not refitted (None) is never gated
    recs, cams = _video(cube, {0: [0, 1, 3, 4]})
    for fit, cap, trusted in ((0.6, 0.55, False), (0.5, 0.55, True), (0.6, 1.0, True), (None, 0.01, True)):
        track = [WorldTrack(0, 2, 7, _at(0.0), fit_rel=fit)]
        out, summary = _complete(cube, recs, cams, track, CompleteConfig(max_fit_rel=cap))
        assert summary["untrusted"] == (0 if trusted else 1)
        assert sum(r.source == "track" for r in out) == (1 if trusted else 0)
    out, _ = _complete(cube, recs, cams, [WorldTrack(0, 2, 7, _at(0.0), fit_rel=0.6)],
                       CompleteConfig(max_fit_rel=0.55, drop_untrusted=True))
    assert out == []


def test_a_part_already_reported_is_not_added_twice(cube: ModelGeometry) -> None:
    # track 1 holds the same part as track 0 in frame 2 (fragmented tracks): no completion of track 0 there
    recs, cams = _video(cube, {0: [0, 1, 3, 4]})
    T2 = cams[2].inverse() @ _at(0.0)
    box2 = project_visible(cube, T2, K, _far(), CompleteConfig()).box_xyxy
    recs.append(_Rec(2, "000002.png", 1, 2, 0.9, box2 + 1.0, T2))
    out, summary = _complete(cube, recs, cams, [WorldTrack(0, 2, 7, _at(0.0))], CompleteConfig(drop_short=False))
    assert summary["added"] == {} and len(out) == len(recs)
    # another class there does not count
    other = [replace(r, label=3) if r.track_id == 1 else r for r in recs]
    out, _ = _complete(cube, other, cams, [WorldTrack(0, 2, 7, _at(0.0))], CompleteConfig(drop_short=False))
    assert sum(r.source == "track" for r in out) == 1


def test_a_track_projects_only_into_frames_of_its_world(cube: ModelGeometry) -> None:
    recs, cams = _video(cube, {0: [0, 1, 3, 4]})
    c = TrackCompleter(CompleteConfig(), [WorldTrack(0, 2, 7, _at(0.0), world=1)], recs, lambda oid: cube)
    for i, T in enumerate(cams):  # frame 2 registered in another (ego) world than the track's
        c.frame(i, f"{i:06d}.png", K, T, _far(), world=2 if i == 2 else 1)
    out, summary = c.result()
    assert summary["untrusted"] == 0 and all(r.source == "detector" for r in out)
    c = TrackCompleter(CompleteConfig(), [WorldTrack(0, 2, 7, _at(0.0), world=1)], recs, lambda oid: cube)
    for i, T in enumerate(cams):
        c.frame(i, f"{i:06d}.png", K, T, _far(), world=1)
    assert [r.frame for r in c.result()[0] if r.source == "track"] == [2]


def test_frames_without_camera_pose_or_depth_get_nothing(cube: ModelGeometry) -> None:
    recs, cams = _video(cube, {0: [0, 1, 3, 4]})
    c = TrackCompleter(CompleteConfig(), [WorldTrack(0, 2, 7, _at(0.0))], recs, lambda oid: cube)
    for i, T in enumerate(cams):
        c.frame(i, f"{i:06d}.png", K, None if i == 2 else T, _far())
    assert all(r.source == "detector" for r in c.result()[0])
    out, _ = _complete(cube, recs, cams, [WorldTrack(0, 2, 7, _at(0.0))], depth=np.full(SHAPE, np.nan))
    assert all(r.source == "detector" for r in out)  # no depth: not trusted, nothing added


class _Misses:
    """The oracle detector, missing the hot stab in one frame."""

    name = "oracle"

    def __init__(self, scene: Path, frame: str) -> None:
        from cadalign.testing.oracle import OracleConfig, OracleDetector

        self.inner, self.frame, self.current = OracleDetector(scene, OracleConfig()), frame, None

    def for_frame(self, name: str) -> None:
        self.inner.for_frame(name)
        self.current = name

    def detect(self, image: np.ndarray, K: np.ndarray) -> list:
        dets = self.inner.detect(image, K)
        names = self.inner.classes.names
        return [d for d in dets if self.current != self.frame or names[int(d.label)] != "hot_stab"]


def _infer_missing(tiny_sim: Path, tiny_structure, out: Path, depth: bool = True, **cfg) -> list[str]:
    """``infer`` on the tiny simulation with completion, the detector missing the hot stab in frame 2; the frames."""
    from cadalign.infer.config import InferConfig
    from cadalign.infer.detect import resolve_scene_dir
    from cadalign.infer.run import calibration_from_scene, run

    scene = resolve_scene_dir(tiny_sim)
    frames = sorted(p.name for p in (tiny_sim / "frames").iterdir())
    det = _Misses(scene, frames[2])
    run(replace(InferConfig(), complete=CompleteConfig(enabled=True), **cfg), tiny_sim / "frames", det,
        tiny_structure.models, det.inner.classes.names, out, calib=calibration_from_scene(scene),
        detector_info={"kind": "test"}, depth_scene=scene if depth else None, gt_scene=scene if depth else None)
    return frames


def test_infer_completes_a_missed_part(tiny_sim: Path, tiny_structure, tmp_path: Path) -> None:
    from cadalign.infer.run import read_poses
    from cadalign.io import read_image, read_json

    out = tmp_path / "out"
    frames = _infer_missing(tiny_sim, tiny_structure, out)
    recs = read_poses(out / "poses.jsonl")
    added = [r for r in recs if r.source == "track"]
    assert len(added) == 1 and added[0].frame_name == frames[2] and added[0].class_name == "hot_stab"
    assert added[0].mask is not None
    lines = [json.loads(x) for x in (out / "poses.jsonl").read_text().splitlines()]
    assert [x["source"] for x in lines].count("track") == 1
    ev = read_json(out / "eval.json")
    assert ev["detector"]["per_class"]["hot_stab"]["detection"]["fn"] == 1  # the network's miss stays on record
    assert ev["fused"]["per_class"]["hot_stab"]["detection"]["f1"] == 1.0  # completion fills it
    assert ev["fused"]["per_class"]["hot_stab"]["t_err_m"]["mean"] < 0.02
    t = read_json(out / "timings.json")
    assert t["poses"] == len(recs) and t["stages_ms"]["complete"] > 0
    per_frame = sum(t["stages"][k]["mean_ms"] for k in ("detector", "identify", "refinement", "temporal"))
    assert t["pipeline_ms_per_frame"] == pytest.approx(per_frame + t["stages_ms"]["complete"])
    # the overlay is drawn again with the completed part: its wireframe is in the frame the detector missed it in
    video = iio.mimread(out / "overlay.mp4")
    raw = read_image(tiny_sim / "frames" / frames[2]).astype(float)
    x0, y0, x1, y1 = np.round(added[0].box_xyxy).astype(int)
    assert len(video) == 4
    assert np.abs(video[2][y0:y1, x0:x1].astype(float) - raw[y0:y1, x0:x1]).mean() > 30  # ~9 undrawn (compression)
    # eval pose on the folder: the detector's section scores the detections, the fused one the completed records
    res = CliRunner().invoke(app, ["eval", "pose", str(out), "--gt", str(tiny_sim), "--out", str(tmp_path / "ev")])
    assert res.exit_code == 0, res.output
    ev2 = read_json(tmp_path / "ev" / "eval.json")
    assert ev2["detector"]["per_class"]["hot_stab"]["detection"]["fn"] == 1
    assert ev2["fused"]["per_class"]["hot_stab"]["detection"]["f1"] == 1.0
    # the trusted tracks' detections report their projected boxes and keep the network's: eval pose scores the
    # network's in its detector section (moved 60 px off here, the reported ones score nothing in the fused one)
    assert all(x["box_xyxy_detector"] is not None for x in lines if x["source"] == "detector")
    moved = tmp_path / "moved"
    moved.mkdir()
    (moved / "frames.json").write_text((out / "frames.json").read_text())
    for x in lines:
        x["box_xyxy"] = [v + 60.0 for v in x["box_xyxy"]]
        x["mask_rle"] = None
    (moved / "poses.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    assert np.allclose(read_poses(moved / "poses.jsonl")[0].box_detector, lines[0]["box_xyxy_detector"])
    res = CliRunner().invoke(app, ["eval", "pose", str(moved), "--gt", str(tiny_sim), "--out", str(tmp_path / "ev3")])
    assert res.exit_code == 0, res.output
    ev3 = read_json(tmp_path / "ev3" / "eval.json")
    assert ev3["detector"]["per_class"]["hot_stab"]["detection"]["fn"] == 1
    assert ev3["detector"]["per_class"]["hot_stab"]["detection"]["tp"] == ev2["detector"]["per_class"]["hot_stab"][
        "detection"]["tp"] > 0
    assert ev3["fused"]["per_class"]["hot_stab"]["detection"]["tp"] == 0


def test_infer_completes_without_camera_poses_in_the_ego_world(tiny_sim: Path, tiny_structure, tmp_path: Path) -> None:
    from cadalign.infer.config import TemporalConfig
    from cadalign.infer.run import read_poses
    from cadalign.io import read_json

    out = tmp_path / "out"  # ego: the camera poses registered on the parts
    frames = _infer_missing(tiny_sim, tiny_structure, out, overlay=False, temporal=TemporalConfig(mode="ego"))
    added = [r for r in read_poses(out / "poses.jsonl") if r.source == "track"]
    assert len(added) == 1 and added[0].frame_name == frames[2] and added[0].class_name == "hot_stab"
    ev = read_json(out / "eval.json")
    assert ev["fused"]["per_class"]["hot_stab"]["detection"]["f1"] == 1.0
    assert ev["fused"]["per_class"]["hot_stab"]["t_err_m"]["mean"] < 0.03


def test_infer_without_depth_leaves_the_records(tiny_sim: Path, tiny_structure, tmp_path: Path,
                                                caplog: pytest.LogCaptureFixture) -> None:
    from cadalign.infer.run import read_poses

    _infer_missing(tiny_sim, tiny_structure, tmp_path / "out", depth=False, overlay=False)
    assert all(r.source == "detector" for r in read_poses(tmp_path / "out" / "poses.jsonl"))
    assert "track completion needs" in caplog.text


def test_min_detected_needs_the_part_detected_in_that_share_of_its_views(cube: ModelGeometry) -> None:
    recs, cams = _video(cube, {0: [0, 1, 3, 4]})  # in sight in 5 frames, detected in 4
    track = [WorldTrack(0, 2, 7, _at(0.0))]
    out, _ = _complete(cube, recs, cams, track, CompleteConfig(min_detected=0.8))
    assert sum(r.source == "track" for r in out) == 1
    out, summary = _complete(cube, recs, cams, track, CompleteConfig(min_detected=0.81))
    assert summary["untrusted"] == 1 and all(r.source == "detector" for r in out)


def test_smoothing_gives_a_tracks_detections_its_world_pose(cube: ModelGeometry) -> None:
    recs, cams = _video(cube, {0: [0, 1, 3, 4]})
    off = Rigid3(recs[0].T_cam_from_obj.R, recs[0].T_cam_from_obj.t + [0.02, 0.0, 0.0])  # a running mean's lag
    recs[0] = replace(recs[0], T_cam_from_obj=off)
    track = [WorldTrack(0, 2, 7, _at(0.0))]
    out, _ = _complete(cube, recs, cams, track)
    first = next(r for r in out if r.frame == 0)
    assert np.allclose(first.T_cam_from_obj.t, (cams[0].inverse() @ _at(0.0)).t)
    out, _ = _complete(cube, recs, cams, track, CompleteConfig(smooth=False))
    assert np.allclose(next(r for r in out if r.frame == 0).T_cam_from_obj.t, off.t)
    # an untrusted track keeps its poses
    far = [replace(r, box_xyxy=r.box_xyxy + 30.0) for r in recs]
    out, _ = _complete(cube, far, cams, track)
    assert np.allclose(next(r for r in out if r.frame == 0).T_cam_from_obj.t, off.t)


def test_reprojection_gives_a_trusted_tracks_detections_its_projected_box_and_mask(cube: ModelGeometry) -> None:
    recs, cams = _video(cube, {0: [0, 1, 3, 4]})
    exact = {r.frame: r.box_xyxy.copy() for r in recs}
    loose = [replace(r, box_xyxy=r.box_xyxy + np.array([-3.0, 0.0, 1.0, 2.0])) for r in recs]  # e.g. a handle's box
    track = [WorldTrack(0, 2, 7, _at(0.0))]
    out, summary = _complete(cube, loose, cams, track)
    own = [r for r in out if r.source == "detector"]
    assert summary["untrusted"] == 0 and len(own) == 4
    for r in own:
        assert np.allclose(r.box_xyxy, exact[r.frame]) and isinstance(r.mask, CroppedMask)
        assert np.allclose(r.box_detector, exact[r.frame] + [-3.0, 0.0, 1.0, 2.0])  # the network's box stays known
        x0, y0, x1, y1 = r.box_xyxy.astype(int)
        assert r.mask.full(SHAPE)[y0:y1, x0:x1].all() and r.mask.full(SHAPE).sum() == (x1 - x0) * (y1 - y0)
    assert next(r for r in out if r.source == "track").box_detector is None  # frame 2: no network box
    # completion run again on its own output (records read back from poses.jsonl) keeps the network's boxes
    again, _ = _complete(cube, own, cams, track)
    assert all(np.allclose(r.box_detector, exact[r.frame] + [-3.0, 0.0, 1.0, 2.0])
               for r in again if r.source == "detector")
    assert [r.box_detector for r in again if r.source == "track"] == [None]
    out, _ = _complete(cube, loose, cams, track, CompleteConfig(reproject=False))
    assert all(np.allclose(r.box_xyxy, exact[r.frame] + [-3.0, 0.0, 1.0, 2.0]) and r.mask is None
               and r.box_detector is None for r in out if r.source == "detector")
    # an untrusted track keeps the network's boxes
    far = [replace(r, box_xyxy=r.box_xyxy + 30.0) for r in recs]
    out, _ = _complete(cube, far, cams, track)
    assert all(np.allclose(r.box_xyxy, exact[r.frame] + 30.0) for r in out)


def test_accurate_on_a_video_without_parts_gives_empty_poses(tiny_sim: Path, tmp_path: Path) -> None:
    from cadalign.io import read_json, write_image

    frames = tmp_path / "water"
    for i in range(3):
        write_image(frames / f"blank_{i}.png", np.full((120, 160, 3), 30, np.uint8))
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["infer", str(frames), "--oracle-gt", str(tiny_sim), "--cad",
                                   str(tiny_sim.parent / "tiny.toml"), "--out", str(out), "--preset", "accurate",
                                   "--depth", str(tiny_sim)])
    assert res.exit_code == 0, res.output
    assert (out / "poses.jsonl").read_text() == ""
    t = read_json(out / "timings.json")
    assert t["frames"] == 3 and t["poses"] == 0 and "complete" in t["stages_ms"]

"""Pipeline pieces on the tiny simulation: model identification, oracle noise, evaluation of exact poses."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from cadalign.cad.model import CadModel
from cadalign.formats.bop import BopScene
from cadalign.formats.class_map import load_class_map
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.config import PRESETS
from cadalign.infer.detect import resolve_scene_dir
from cadalign.infer.pipeline import PosePipeline
from cadalign.metrics import pose as pm
from cadalign.metrics.pose import rotation_error_deg
from cadalign.metrics.pose_eval import (
    PoseEvalConfig,
    PosePrediction,
    evaluate_scene,
    gt_instances,
    load_bop_models,
    table_markdown,
)
from cadalign.testing.oracle import OracleConfig, OracleDetector
from cadalign.types import Rigid3


@pytest.fixture(scope="module")
def scene(tiny_sim: Path) -> Path:
    return resolve_scene_dir(tiny_sim)


def test_oracle_noise_has_the_requested_size(scene: Path) -> None:
    exact = OracleDetector(scene, OracleConfig(noise_t_m=0.0, noise_r_deg=0.0)).for_frame("000000.png")
    noisy = OracleDetector(scene, OracleConfig(noise_t_m=0.05, noise_r_deg=4.0, seed=3)).for_frame("000000.png")
    a, b = exact.detect(None, None), noisy.detect(None, None)
    assert len(a) == len(b) >= 2
    for d0, d1 in zip(a, b, strict=True):
        assert d0.obj_id is None  # like a network: the class only
        assert 0.0 < np.linalg.norm(d1.t_cam_from_obj_m - d0.t_cam_from_obj_m) < 0.2
        assert 0.0 < rotation_error_deg(d1.R_cam_from_obj, d0.R_cam_from_obj) < 12.0
    assert exact.for_frame("not_a_frame.png").detect(None, None) == []


def test_identification_picks_the_model_whose_silhouette_fits(scene: Path, tiny_structure) -> None:
    models = dict(tiny_structure.models)
    # a decoy of the valve's class: the structure block renamed, far from the valve's shape
    models[9] = CadModel("decoy", models[1].vertices_m * 0.3, models[1].faces, class_name="valve")
    det = OracleDetector(scene, OracleConfig(noise_t_m=0.0, noise_r_deg=0.0))
    pipe = PosePipeline(det, models, tiny_structure.class_names, PRESETS["fast"])
    valve = next(d for d in det.for_frame("000002.png").detect(None, None) if d.label == 2)
    K = det.scene.frame(2).camera.K
    T = Rigid3(valve.R_cam_from_obj, valve.t_cam_from_obj_m)
    assert sorted(pipe.candidates(2)) == [2, 9]
    assert pipe.identify(valve, T, K)[0] == 2  # by silhouette
    assert pipe.identify(valve, T, K, det.scene.depth_m(2))[0] == 2  # by depth
    assert pipe.identify(replace(valve, obj_id=9), T, K) == (9, T)  # a reported model id wins


def test_a_box_overlapping_the_previous_frames_reuses_its_model(scene: Path, tiny_structure, monkeypatch) -> None:
    """With two models in the valve class, the same valve box on consecutive frames is identified once; frame gaps,
    reuse_box_iou = 0 and a box that moved away identify again."""
    models = dict(tiny_structure.models)
    models[9] = CadModel("decoy", models[1].vertices_m * 0.3, models[1].faces, class_name="valve")
    det = OracleDetector(scene, OracleConfig(noise_t_m=0.0, noise_r_deg=0.0))
    valve = next(d for d in det.for_frame("000002.png").detect(None, None) if d.label == 2)
    K = det.scene.frame(2).camera.K
    image = np.zeros((120, 160, 3), np.uint8)

    class Fixed:  # the same valve detection on every frame, its box shifted by `dx` pixels
        dx = 0.0

        def detect(self, image, K):
            return [replace(valve, box_xyxy=np.asarray(valve.box_xyxy, float) + [self.dx, 0, self.dx, 0])]

    def run(frames: list[int], reuse: float, shifts: dict[int, float] | None = None) -> int:
        fixed = Fixed()
        pipe = PosePipeline(fixed, models, tiny_structure.class_names, replace(PRESETS["fast"], reuse_box_iou=reuse))
        calls = []
        real = pipe.identify
        monkeypatch.setattr(pipe, "identify", lambda *a, **k: calls.append(1) or real(*a, **k))
        for f in frames:
            fixed.dx = (shifts or {}).get(f, 0.0)
            records, _ = pipe.process(f, f"{f:06d}.png", image, K)
            assert [r.obj_id for r in records] == [2]
        return len(calls)

    assert run([0, 1, 2], 0.5) == 1
    assert run([0, 1, 2], 0.0) == 3
    assert run([0, 2, 4], 0.5) == 3  # not consecutive frames
    width = float(valve.box_xyxy[2] - valve.box_xyxy[0])
    assert run([0, 1], 0.5, {1: 0.8 * width}) == 2  # the box moved: IoU < 0.5


def test_exact_poses_score_perfectly_and_a_shift_is_measured(scene: Path) -> None:
    cmap = load_class_map(scene)
    models = load_bop_models(scene.parent.parent / "models")
    preds, shifted = [], []
    for im_id in (0, 1):
        for g in gt_instances(BopScene(scene), im_id, cmap.class_of_obj):
            if cmap.names[g.label] == "structure":
                continue
            preds.append(PosePrediction(im_id, g.label, 1.0, g.box_xyxy, g.T_cam_from_obj, None, g.mask))
            T = g.T_cam_from_obj
            shifted.append(replace(preds[-1], T_cam_from_obj=Rigid3(T.R, T.t + [0.0, 0.0, 0.05])))
    rep = evaluate_scene(preds, scene, models, cmap.names, cmap.class_of_obj, PoseEvalConfig(), [0, 1])
    assert rep["detection"]["f1"] == 1.0 and rep["overall"]["t_err_m"]["max"] < 1e-9
    assert rep["overall"]["ar_mssd"] == 1.0 and rep["overall"]["ar_mspd"] == 1.0
    assert all(r["mask_iou"] == 1.0 for r in rep["matches"]) and rep["misses"] == []
    rep = evaluate_scene(shifted, scene, models, cmap.names, cmap.class_of_obj, PoseEvalConfig(), [0, 1])
    assert rep["overall"]["t_err_m"]["mean"] == pytest.approx(0.05)
    assert rep["overall"]["r_err_deg"]["max"] < 1e-6
    # 5 cm is under the smallest MSSD threshold (5 % of 0.75 m = 3.75 cm) for no valve: recall below 1
    assert rep["per_class"]["valve"]["ar_mssd"] < 1.0
    missed = evaluate_scene(preds[:1], scene, models, cmap.names, cmap.class_of_obj, PoseEvalConfig(), [0, 1])
    assert missed["detection"]["fn"] == len(preds) - 1 and missed["detection"]["precision"] == 1.0
    # the misses are listed (frame, GT index), the one hit is not
    targets = [(im_id, g.gt_idx) for im_id in (0, 1) for g in gt_instances(BopScene(scene), im_id, cmap.class_of_obj)
               if cmap.names[g.label] != "structure"]
    assert sorted((m["im_id"], m["gt_idx"]) for m in missed["misses"]) == sorted(targets[1:])
    assert all(0.0 < m["visib_fract"] <= 1.0 and len(m["box_xyxy"]) == 4 for m in missed["misses"])


def _valve_targets(scene: Path) -> tuple:
    """The class map, the evaluation models and the (frame, target) pairs of the valves of frames 0 and 1."""
    cmap = load_class_map(scene)
    models = load_bop_models(scene.parent.parent / "models")
    valves = [(im_id, g) for im_id in (0, 1) for g in gt_instances(BopScene(scene), im_id, cmap.class_of_obj)
              if cmap.names[g.label] == "valve"]
    return cmap, models, valves


def test_the_evaluation_says_which_kind_of_error_costs_what(scene: Path) -> None:
    """Per class, the false positives and misses by TIDE's kinds, and the F1 were each kind fixed: boxes cut to
    their left third are localization errors (their fix restores F1 1), an extra box far off is background."""
    cmap, models, valves = _valve_targets(scene)
    preds = []
    for im_id, g in valves:
        box = g.box_xyxy.copy()
        if im_id == 1:
            box[2] = box[0] + (box[2] - box[0]) / 3  # IoU 1/3: a miss and a false positive
        preds.append(PosePrediction(im_id, g.label, 1.0, box, g.T_cam_from_obj, g.obj_id, g.mask))
    n1 = sum(p.im_id == 1 for p in preds)
    far = np.array([-50.0, -50.0, -40.0, -40.0])  # off the image: no target near it
    preds.append(replace(preds[0], box_xyxy=far, score=0.5))
    rep = evaluate_scene(preds, scene, models, cmap.names, cmap.class_of_obj, PoseEvalConfig(), [0, 1])
    v = rep["per_class"]["valve"]
    assert v["detection"]["fp"] == n1 + 1 and v["detection"]["fn"] == n1
    e = v["errors"]
    assert e["fp"] == {"class": 0, "duplicate": 0, "localization": n1, "both": 0, "background": 1}
    assert e["fn"] == {"localization": n1, "class": 0, "missed": 0}
    assert e["f1_fixed"]["localization"] == pytest.approx(
        pm.DetectionCounts(v["detection"]["tp"] + n1, 1, 0).f1)
    assert e["f1_fixed"]["background"] > v["detection"]["f1"] == e["f1_fixed"]["duplicate"]
    assert "| valve | " in table_markdown(rep).split("Detection errors")[1]


def test_the_evaluation_counts_detections_given_the_wrong_model(scene: Path) -> None:
    """Per class: how many matched detections carry a model id, how many the right one, and their errors."""
    cmap, models, valves = _valve_targets(scene)
    preds = []
    for im_id, g in valves:
        T = g.T_cam_from_obj
        wrong = im_id == 1  # frame 1's valves: a wrong model id and a pose 0.2 m off
        preds.append(PosePrediction(im_id, g.label, 1.0, g.box_xyxy, Rigid3(T.R, T.t + [0.0, 0.0, 0.2 * wrong]),
                                    999 if wrong else g.obj_id, g.mask))
    n1 = sum(p.im_id == 1 for p in preds)
    assert 0 < n1 < len(preds)
    rep = evaluate_scene(preds, scene, models, cmap.names, cmap.class_of_obj, PoseEvalConfig(), [0, 1])
    ident = rep["per_class"]["valve"]["model_id"]
    assert ident["n"] == len(preds) and ident["right"] == len(preds) - n1
    assert ident["t_err_m_right"]["max"] < 1e-9  # the right ones are exact; the class mean is not
    assert rep["per_class"]["valve"]["t_err_m"]["mean"] == pytest.approx(0.2 * n1 / len(preds))
    assert f"| {len(preds) - n1}/{len(preds)} | 0.000 m / 0.00 deg |" in table_markdown(rep)
    # predictions without a model id (a network alone) are not counted
    bare = [replace(p, obj_id=None) for p in preds]
    rep = evaluate_scene(bare, scene, models, cmap.names, cmap.class_of_obj, PoseEvalConfig(), [0, 1])
    assert rep["per_class"]["valve"]["model_id"]["n"] == 0 and "| - | - |" in table_markdown(rep)


def test_preset_none_reports_the_detector_pose_unchanged(scene: Path, tiny_structure) -> None:
    det = OracleDetector(scene, OracleConfig(seed=1))
    pipe = PosePipeline(det, tiny_structure.models, tiny_structure.class_names, PRESETS["none"])
    K = det.scene.frame(1).camera.K
    records, times = pipe.process(1, "000001.png", np.zeros((120, 160, 3), np.uint8), K)
    assert records and {"detector", "identify", "refinement", "temporal"} <= set(times)
    for r in records:
        assert r.refine_iters == {} and r.track_id == -1
        np.testing.assert_array_equal(r.T_refined.matrix(), r.T_detector.matrix())
        np.testing.assert_array_equal(r.T_cam_from_obj.matrix(), r.T_detector.matrix())


def test_a_class_threshold_keeps_that_class_below_the_score_threshold(scene: Path, tiny_structure) -> None:
    class Unsure:  # the oracle's detections at score 0.4
        def __init__(self, det: OracleDetector) -> None:
            self.det = det

        def for_frame(self, name: str) -> Unsure:
            self.frame = self.det.for_frame(name)
            return self

        def detect(self, image: object, K: object) -> list:
            return [replace(d, score=0.4) for d in self.frame.detect(image, K)]

    det = Unsure(OracleDetector(scene, OracleConfig(seed=1)))
    K = det.det.scene.frame(1).camera.K
    image = np.zeros((120, 160, 3), np.uint8)
    kept = {}
    for classes, thresh in (({}, 0.5), ({"valve": 0.3}, 0.5), ({"hot_stab": 0.3}, 0.5), ({}, 0.3)):
        cfg = replace(PRESETS["none"], class_score_thresh=classes, score_thresh=thresh)
        pipe = PosePipeline(det.for_frame("000001.png"), tiny_structure.models, tiny_structure.class_names, cfg)
        kept[(*classes, thresh)] = sorted(r.class_name for r in pipe.process(1, "000001.png", image, K)[0])
    assert kept[(0.5,)] == [] and {"valve", "hot_stab"} <= set(kept[(0.3,)])
    for name in ("valve", "hot_stab"):  # each class's own threshold keeps that class only
        assert kept[(name, 0.5)] == [c for c in kept[(0.3,)] if c == name]
    assert replace(PRESETS["none"], class_score_thresh={"valve": 0.3}).detector_score_thresh == 0.3
    assert PRESETS["accurate"].detector_score_thresh == PRESETS["accurate"].score_thresh
    with pytest.raises(ValueError, match="class_score_thresh"):
        replace(PRESETS["none"], class_score_thresh={"valve": 1.5})


def test_calibration_uses_only_metric_poses(tmp_path: Path, tiny_sim: Path, caplog) -> None:
    from cadalign.infer.run import load_calibration
    from cadalign.io import read_json, write_json

    cams = read_json(scene_cameras := resolve_scene_dir(tiny_sim) / "cameras.json")
    metric = load_calibration(scene_cameras)
    assert set(metric.T_world_from_cam_of) == set(cams["frames"]) and metric.K("unlisted.png").shape == (3, 3)
    write_json(sfm := tmp_path / "cameras.json", {**cams, "units": "sfm"})
    with caplog.at_level("WARNING"):
        assert load_calibration(sfm).T_world_from_cam_of == {}  # SfM units: intrinsics only
    assert f"{sfm} is in sfm units, not metres: its camera poses are not used" in caplog.text


def test_no_predictions_score_zero(scene: Path) -> None:
    cmap = load_class_map(scene)
    rep = evaluate_scene([], scene, load_bop_models(scene.parent.parent / "models"), cmap.names, cmap.class_of_obj,
                         PoseEvalConfig(), [0])
    assert rep["detection"]["tp"] == 0 and rep["detection"]["fn"] > 0 and rep["detection"]["f1"] == 0.0
    assert rep["overall"]["ar_mssd"] == 0.0 and rep["overall"]["t_err_m"]["n"] == 0


def test_min_box_side_makes_small_targets_dont_care(scene: Path) -> None:
    """GT boxes with a shorter side under ``min_box_side_px`` are neither misses nor hits."""
    cmap = load_class_map(scene)
    models = load_bop_models(scene.parent.parent / "models")
    gts = [g for g in gt_instances(BopScene(scene), 0, cmap.class_of_obj) if cmap.names[g.label] != "structure"
           and g.visib_fract >= 0.1]
    sides = sorted(min(g.box_xyxy[2] - g.box_xyxy[0], g.box_xyxy[3] - g.box_xyxy[1]) for g in gts)
    assert len(sides) >= 2 and sides[0] < sides[-1]
    cut = (sides[0] + sides[-1]) / 2
    big = [g for g in gts if min(g.box_xyxy[2] - g.box_xyxy[0], g.box_xyxy[3] - g.box_xyxy[1]) >= cut]
    preds = [PosePrediction(0, g.label, 1.0, g.box_xyxy, g.T_cam_from_obj) for g in big]
    strict = evaluate_scene(preds, scene, models, cmap.names, cmap.class_of_obj, PoseEvalConfig(), [0])
    assert strict["detection"]["fn"] == len(gts) - len(big) > 0
    cfg = PoseEvalConfig(min_box_side_px=cut)
    rep = evaluate_scene(preds, scene, models, cmap.names, cmap.class_of_obj, cfg, [0])
    assert rep["detection"]["fn"] == 0 and rep["detection"]["tp"] == len(big) and rep["detection"]["f1"] == 1.0
    assert rep["config"]["min_box_side_px"] == cut


def test_a_detection_on_an_established_track_starts_from_the_track(scene: Path, tiny_structure, monkeypatch) -> None:
    """A static camera sees the same valve each frame; from frame 3 the network's pose is 60 deg and 30 % of its
    distance off (far beyond half the valve's diameter from the track). The track
    fused from frames 0-2 gives the model without identifying again and a start that refinement keeps ("pose");
    "off" identifies every frame, and the refined pose stays near the network's."""
    models = dict(tiny_structure.models)
    models[9] = CadModel("decoy", models[1].vertices_m * 0.3, models[1].faces, class_name="valve")
    det = OracleDetector(scene, OracleConfig(noise_t_m=0.0, noise_r_deg=0.0))
    valve = next(d for d in det.for_frame("000002.png").detect(None, None) if d.label == 2)
    K, depth = det.scene.frame(2).camera.K, det.scene.depth_m(2)
    truth = next(g.T_cam_from_obj for g in det.scene.frame(2).instances if g.obj_id == 2)
    off = axis_angle_to_matrix(np.array([0.0, 0.0, np.radians(60.0)])) @ valve.R_cam_from_obj

    class Turning:
        frame = 0

        def detect(self, image, K):
            far = np.asarray(valve.t_cam_from_obj_m, float) * 1.3  # and its distance 30 % long, as networks are
            return [valve if self.frame < 3 else replace(valve, R_cam_from_obj=off, t_cam_from_obj_m=far)]

    def run(track_init: str) -> tuple[int, float]:
        net = Turning()
        cfg = replace(PRESETS["fast"], reuse_box_iou=0.0, track_init=track_init)
        pipe = PosePipeline(net, models, tiny_structure.class_names, cfg)
        calls = []
        real = pipe.identify
        monkeypatch.setattr(pipe, "identify", lambda *a, **k: calls.append(1) or real(*a, **k))
        for f in range(6):
            net.frame = f
            records, _ = pipe.process(f, f"{f:06d}.png", np.zeros((120, 160, 3), np.uint8), K, depth, Rigid3.identity())
            assert [r.obj_id for r in records] == [2]
        return len(calls), rotation_error_deg(records[0].T_refined.R, truth.R)

    calls, err = run("pose")
    assert calls == 3 and err < 2.0
    calls, err = run("model")  # the track's model without identifying, the network's pose as the start
    assert calls == 3 and err > 20.0
    calls, err = run("off")
    assert calls == 6 and err > 20.0


def test_identification_by_view_rejects_a_model_with_surface_where_nothing_is_seen(scene: Path,
                                                                                  tiny_structure) -> None:
    """A decoy holding the whole valve plus a block beside it fits the valve's masked depth points as well as the
    valve does (data -> model); rendered, its block covers pixels where the camera sees far behind it."""
    import trimesh

    models = dict(tiny_structure.models)
    v = models[2]
    lo, hi = v.vertices_m.min(0), v.vertices_m.max(0)
    size = hi - lo
    block = trimesh.creation.box(extents=size * [1.0, 1.0, 0.6])
    block.apply_translation((lo + hi) / 2 + [0.0, 0.0, 0.8 * size[2]])
    both = trimesh.util.concatenate([trimesh.Trimesh(v.vertices_m, v.faces, process=False), block])
    models[0] = CadModel("valve_with_block", np.asarray(both.vertices), np.asarray(both.faces), class_name="valve")
    det = OracleDetector(scene, OracleConfig(noise_t_m=0.0, noise_r_deg=0.0))
    valve = next(d for d in det.for_frame("000002.png").detect(None, None) if d.label == 2)
    K, depth = det.scene.frame(2).camera.K, det.scene.depth_m(2)
    T = Rigid3(valve.R_cam_from_obj, valve.t_cam_from_obj_m)
    cfg = replace(PRESETS["accurate"], identify_score="view")
    by_view = PosePipeline(det, models, tiny_structure.class_names, cfg)
    assert sorted(by_view.candidates(2)) == [0, 2]
    oid, T_v = by_view.identify(valve, T, K, depth)
    assert oid == 2
    assert np.linalg.norm(T_v.t - T.t) < 0.05
    # the data -> model fit alone cannot tell them: the decoy's median point distance is within a few mm, so
    # a decoy fitting a little better (noise) is taken by depth and still rejected by view
    from cadalign.infer.refine import icp_points, pick_fit

    Q = icp_points(depth, np.asarray(valve.mask, bool), K, cfg.refine)
    d = [float(np.median(by_view.geometry(k).tree.query(T.inverse().apply(Q))[0])) for k in (0, 2)]
    assert abs(d[0] - d[1]) < 0.005
    scored = [(0.001, 0, T), (0.002, 2, T)]
    assert scored[pick_fit([0.001, 0.002], [T, T], T, 0.0)][1] == 0
    assert by_view._pick_model_by_view(scored, T, K, np.asarray(valve.mask, bool), depth) == (2, T)
    # without depth the silhouettes are compared as before
    assert by_view.identify(valve, T, K)[0] == 2


def test_view_identification_counts_the_mask_against_a_model_fitted_far_off(scene: Path, tiny_structure) -> None:
    """A candidate whose fit slid metres along the ray covers a few pixels and, judged near its own depth, would
    leave no mask pixel unexplained; judged near the observed depth it explains none of them."""
    models = dict(tiny_structure.models)
    models[0] = CadModel("small_valve", models[2].vertices_m * 0.5, models[2].faces, class_name="valve")
    det = OracleDetector(scene, OracleConfig(noise_t_m=0.0, noise_r_deg=0.0))
    valve = next(d for d in det.for_frame("000002.png").detect(None, None) if d.label == 2)
    K, depth = det.scene.frame(2).camera.K, det.scene.depth_m(2)
    T = Rigid3(valve.R_cam_from_obj, valve.t_cam_from_obj_m)
    far = Rigid3(T.R, T.t * (1.0 + 3.0 / np.linalg.norm(T.t)))  # 3 m farther along the ray
    pipe = PosePipeline(det, models, tiny_structure.class_names, replace(PRESETS["accurate"], identify_score="view"))
    mask = np.asarray(valve.mask, bool)
    assert pipe._pick_model_by_view([(0.001, 0, far), (0.002, 2, T)], T, K, mask, depth) == (2, T)


def test_a_track_is_identified_again_on_a_mask_grown_past_reidentify_growth(scene: Path, tiny_structure,
                                                                            monkeypatch) -> None:
    """Frames 0-2 see half the valve (identified as a decoy), frames 3-5 all of it: with reidentify_growth the
    track's model is checked again on frame 3 and, found wrong, the track retires and the right model goes on."""
    from cadalign.infer.config import RefineConfig

    models = dict(tiny_structure.models)
    models[9] = CadModel("decoy", models[1].vertices_m * 0.3, models[1].faces, class_name="valve")
    det = OracleDetector(scene, OracleConfig(noise_t_m=0.0, noise_r_deg=0.0))
    valve = next(d for d in det.for_frame("000002.png").detect(None, None) if d.label == 2)
    K = det.scene.frame(2).camera.K
    full = np.asarray(valve.mask, bool)
    half = full.copy()
    cols = np.flatnonzero(full.any(0))
    half[:, cols[len(cols) // 2]:] = False
    image = np.zeros((120, 160, 3), np.uint8)

    class Fixed:
        mask = half

        def detect(self, image, K):
            return [replace(valve, mask=self.mask)]

    def run(growth: float, wrong_always: bool) -> tuple[list[int], list[int], int]:
        fixed = Fixed()
        cfg = replace(PRESETS["fast"], refine=RefineConfig(method="none"), reidentify_growth=growth)
        pipe = PosePipeline(fixed, models, tiny_structure.class_names, cfg)
        real, calls = pipe.identify, []

        def identify(d, T, K, depth_m=None):
            calls.append(1)
            small = np.count_nonzero(d.mask) < 0.8 * np.count_nonzero(full)
            return (9, T) if small or wrong_always else real(d, T, K, depth_m)

        monkeypatch.setattr(pipe, "identify", identify)
        oids, tracks = [], []
        for f in range(6):
            fixed.mask = half if f < 3 else full
            records, _ = pipe.process(f, f"{f:06d}.png", image, K, T_world_from_cam=Rigid3.identity())
            oids += [r.obj_id for r in records]
            tracks += [r.track_id for r in records]
        return oids, tracks, len(calls)

    assert np.count_nonzero(full) >= 1.5 * np.count_nonzero(half)
    oids, tracks, calls = run(1.5, False)
    assert oids == [9, 9, 9, 2, 2, 2] and len(set(tracks[:3])) == 1 and tracks[3] != tracks[0]
    assert calls == 2  # frame 0, then the check on frame 3; frames 1-2 reuse the box, 4-5 the new model's box
    oids, tracks, calls = run(0.0, False)  # off: the first decision stands
    assert oids == [9] * 6 and len(set(tracks)) == 1 and calls == 1
    oids, tracks, calls = run(1.5, True)  # the check agrees: same track, and no further check at the same size
    assert oids == [9] * 6 and len(set(tracks)) == 1 and calls == 2

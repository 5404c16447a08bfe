"""Multi-frame refit of a static part's world pose, duplicate tracks (cadalign.infer.track_fit), and the pipeline
handing refitted (also retired) tracks to completion."""

from __future__ import annotations

import math

import numpy as np
import pytest
from infer_testdata import look_at

from cadalign.cad.model import CadModel
from cadalign.cad.procedural import make_part
from cadalign.eval.pose_metrics import rotation_error_deg
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.depth_icp import depth_fit, masked_depth_points
from cadalign.infer.model_geom import ModelGeometry, render_depth
from cadalign.infer.pipeline import PRESETS, PosePipeline
from cadalign.infer.pose_math import Observation
from cadalign.infer.track_fit import (
    FittedTrack,
    RefitConfig,
    TrackPoints,
    duplicates,
    icp_world,
    refit_world_pose,
)
from cadalign.types import Rigid3

K = np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]])
SHAPE = (120, 160)
T_WO = Rigid3(axis_angle_to_matrix(np.array([0.2, -0.1, 0.7])), np.array([1.0, -0.5, 2.0]))


@pytest.fixture(scope="module")
def stab_model() -> CadModel:
    mesh = make_part("hot_stab")  # a probe along y with a T-handle: no symmetry
    return CadModel("hot_stab", np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64),
                    class_name="hot_stab")


@pytest.fixture(scope="module")
def stab(stab_model: CadModel) -> ModelGeometry:
    return ModelGeometry.from_cad(stab_model, 2000)


def _cameras(geom: ModelGeometry, T_wo: Rigid3, n: int, dist: float = 2.5) -> list[Rigid3]:
    """``T_world_from_cam`` of ``n`` cameras on an arc around the part, looking at it."""
    centre = T_wo.apply(geom.samples.mean(0)[None])[0]
    out = []
    for k in range(n):
        a = math.radians(-40 + 80 * k / max(n - 1, 1))
        out.append(look_at(centre + dist * np.array([math.cos(a), math.sin(a), 0.4]), centre))
    return out


def _frame_points(geom: ModelGeometry, T_wo: Rigid3, T_wc: Rigid3) -> np.ndarray:
    """Camera-frame points of the part's exact depth in one view (every mask pixel: a thin part)."""
    z = render_depth(geom, T_wc.inverse() @ T_wo, K, SHAPE)
    mask = np.isfinite(z)
    return masked_depth_points(np.where(mask, z, 0.0), mask, K, 10_000, np.random.default_rng(0), 10_000)


def _views(geom: ModelGeometry, T_wo: Rigid3, n: int = 5, track_id: int = 0,
           pts: TrackPoints | None = None) -> TrackPoints:
    pts = pts or TrackPoints(RefitConfig(points_per_frame=200))
    for T_wc in _cameras(geom, T_wo, n):
        pts.add(track_id, _frame_points(geom, T_wo, T_wc), T_wc)
    return pts


def _flipped(T: Rigid3, geom: ModelGeometry) -> Rigid3:
    """``T`` turned end for end: half a turn about the model's z axis through its centre, moved 0.1 m."""
    c = geom.samples.mean(0)
    R = T.R @ axis_angle_to_matrix(np.array([0.0, 0.0, math.pi]))
    return Rigid3(R, T.apply(c[None])[0] - R @ c + np.array([0.1, 0.0, 0.0]))


def _err(T: Rigid3, T_ref: Rigid3) -> tuple[float, float]:
    return float(np.linalg.norm(T.t - T_ref.t)), rotation_error_deg(T.R, T_ref.R)


def test_track_points_keep_a_subset_per_detection_in_the_world_frame(stab: ModelGeometry) -> None:
    pts = _views(stab, T_WO, n=3)
    P, C = pts.of(0)
    seen = [len(_frame_points(stab, T_WO, T_wc)) for T_wc in _cameras(stab, T_WO, 3)]
    assert max(seen) > 200 and pts.frames(0) == 3 and len(P) == sum(min(n, 200) for n in seen)
    assert P.shape == C.shape
    # world points on the part's surface at its world pose (within the model samples' spacing), not end for end
    assert depth_fit(stab, T_WO, P) < 0.01 < depth_fit(stab, _flipped(T_WO, stab), P)
    assert len(np.unique(C, axis=0)) == 3
    assert pts.frames(7) == 0 and pts.of(7)[0].shape == (0, 3)


def test_refit_turns_an_end_for_end_flip_back(stab: ModelGeometry) -> None:
    P, C = _views(stab, T_WO).of(0)
    start = _flipped(T_WO, stab)
    plain = icp_world(stab, [start], P, C, 30, 0.005)[0]
    assert _err(plain, T_WO)[1] > 90  # ICP from the fused pose alone stays end for end
    res = refit_world_pose(stab, start, P, C, RefitConfig())
    assert res is not None
    t_err, r_err = _err(res.T_world_from_obj, T_WO)
    assert t_err < 0.005 and r_err < 1.0
    assert res.fit_m < res.fused_fit_m and res.starts > 100


def test_refit_keeps_a_pose_that_fits(stab: ModelGeometry) -> None:
    P, C = _views(stab, T_WO).of(0)
    start = Rigid3(axis_angle_to_matrix(np.array([0.0, 0.02, 0.0])) @ T_WO.R, T_WO.t + 0.01)
    res = refit_world_pose(stab, start, P, C, RefitConfig())
    t_err, r_err = _err(res.T_world_from_obj, T_WO)
    assert t_err < 0.003 and r_err < 0.5


def test_too_few_points_leave_the_fused_pose() -> None:
    geom = ModelGeometry.from_cad(CadModel("p", *_box_mesh()), 200)
    P = np.random.default_rng(0).normal(size=(10, 3))
    assert refit_world_pose(geom, Rigid3.identity(), P, np.zeros_like(P), RefitConfig()) is None


def _box_mesh() -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.box(extents=(0.3, 0.2, 0.1))
    return np.asarray(m.vertices), np.asarray(m.faces)


def _fitted(track_id: int, geom: ModelGeometry, T: Rigid3, P: np.ndarray, frames: int, label: int = 3
            ) -> FittedTrack:
    return FittedTrack(track_id, label, 0, frames, geom, T, P)


def test_the_track_explaining_both_tracks_points_is_kept(stab: ModelGeometry) -> None:
    right = _views(stab, T_WO, n=4).of(0)[0]
    # a second track of the same part, fused end for end from three of its views: its pose explains only part of
    # its own points, and the first track's pose explains them all
    cams = _cameras(stab, T_WO, 3)
    wrong_pts = np.concatenate([T_wc.apply(_frame_points(stab, T_WO, T_wc)) for T_wc in cams])
    wrong = _flipped(T_WO, stab)
    cfg = RefitConfig()
    assert duplicates([_fitted(0, stab, T_WO, right, 4), _fitted(1, stab, wrong, wrong_pts, 3)], cfg) == {1: 0}
    # the wrong one with more detections: still the right one is kept
    assert duplicates([_fitted(0, stab, T_WO, right, 2), _fitted(1, stab, wrong, wrong_pts, 9)], cfg) == {1: 0}
    # another class, another part 2 m away, or the test off: no duplicates
    assert duplicates([_fitted(0, stab, T_WO, right, 4), _fitted(1, stab, wrong, wrong_pts, 3, label=2)], cfg) == {}
    far = Rigid3(T_WO.R, T_WO.t + np.array([2.0, 0, 0]))
    assert duplicates([_fitted(0, stab, T_WO, right, 4), _fitted(1, stab, far, right + [2.0, 0, 0], 3)], cfg) == {}
    assert duplicates([_fitted(0, stab, T_WO, right, 4), _fitted(1, stab, wrong, wrong_pts, 3)],
                      RefitConfig(dup_share=0.0)) == {}


def test_the_pipeline_refits_world_tracks_retired_ones_included(stab_model: CadModel, stab: ModelGeometry) -> None:
    """``world_tracks``: a track fused end for end gets its refitted pose; a retired track with points is handed
    over too (its model was taken for another, which completion's duplicate test then weighs)."""
    pipe = PosePipeline(None, {6: stab_model}, ("background", "structure", "valve", "hot_stab"),
                        PRESETS["accurate"])
    cams = _cameras(stab, T_WO, 5)
    wrong = _flipped(T_WO, stab)
    for f, T_wc in enumerate(cams):  # one track, fused from flipped per-frame poses
        obs = [Observation(3, T_wc.inverse() @ wrong, 6, stab_model.symmetry, stab_model.diameter_m)]
        fused = pipe.fuser.update(f, obs, T_wc)
        pipe.points.add(fused[0].track_id, _frame_points(stab, T_WO, T_wc), T_wc)
    [before] = [tr.T for tr in pipe.fuser.tracks]
    assert _err(before, T_WO)[1] > 90
    [track] = pipe.world_tracks()
    assert _err(track.T_world_from_obj, T_WO)[0] < 0.005 and _err(track.T_world_from_obj, T_WO)[1] < 1.0
    pipe.fuser.retire(track.track_id)
    assert [w.track_id for w in pipe.world_tracks()] == [track.track_id]
    no_refit = PosePipeline(None, {6: stab_model}, pipe.class_names, PRESETS["balanced"])
    assert no_refit.points is None and no_refit.world_tracks() == []

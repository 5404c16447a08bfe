"""Multi-frame refit of a static part's world pose, duplicate tracks (cadalign.infer.refine.track_fit), and the pipeline
handing refitted (also retired) tracks to completion."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from infer_testdata import look_at

from cadalign.cad.model import CadModel
from cadalign.cad.procedural import make_part
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.config import PRESETS, RefitConfig
from cadalign.infer.model_geom import ModelGeometry, render_depth
from cadalign.infer.pipeline import PosePipeline
from cadalign.infer.pose_math import Observation
from cadalign.infer.refine.depth_icp import depth_fit, masked_depth_points
from cadalign.infer.refine.track_fit import (
    FittedTrack,
    TrackPoints,
    TrackView,
    ViewScoring,
    closeness,
    duplicates,
    explained,
    icp_world,
    pick_model,
    refit_world_pose,
    turn_by_view,
    view_score,
)
from cadalign.metrics.pose import rotation_error_deg
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
        pts.add(track_id, _frame_points(geom, T_wo, T_wc), T_wc, _view(geom, T_wo, T_wc))
    return pts


def _view(geom: ModelGeometry, T_wo: Rigid3, T_wc: Rigid3) -> TrackView:
    """The part's view in one frame: its exact mask, and its depth in front of a wall 1 m behind its origin."""
    T = T_wc.inverse() @ T_wo
    z = render_depth(geom, T, K, SHAPE)
    mask = np.isfinite(z)
    view = TrackView.crop(K, T_wc, mask, np.where(mask, z, T.t[2] + 1.0), 1.0)
    assert view is not None
    return view


def _with_handle(model: CadModel) -> CadModel:
    """A decoy of ``model``: the same mesh plus a 0.3 m bar beside it (a longer part of the same class)."""
    import trimesh

    bar = trimesh.creation.box(extents=(0.3, 0.04, 0.04))
    lo, hi = model.vertices_m.min(0), model.vertices_m.max(0)
    bar.apply_translation([hi[0] + 0.15, 0.5 * (lo[1] + hi[1]), 0.5 * (lo[2] + hi[2])])
    V = np.concatenate([model.vertices_m, bar.vertices])
    F = np.concatenate([model.faces, np.asarray(bar.faces) + len(model.vertices_m)])
    return CadModel("decoy", V, F, class_name=model.class_name)


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


def test_a_view_is_cropped_around_the_mask_with_its_intrinsics() -> None:
    mask = np.zeros(SHAPE, bool)
    mask[50:60, 70:74] = True  # 10 x 4 px: grown by 10 + 8 px on each side, clipped to the frame
    depth = np.arange(SHAPE[0] * SHAPE[1], dtype=float).reshape(SHAPE)
    T_wc = Rigid3(np.eye(3), np.array([1.0, 2.0, 3.0]))
    v = TrackView.crop(K, T_wc, mask, depth, 1.0)
    assert v is not None and v.mask.shape == (46, 40) and v.mask.sum() == 40
    assert v.depth_m[0, 0] == depth[32, 52] and v.depth_m.dtype == np.float32
    assert np.allclose(v.K[:2, 2], K[:2, 2] - [52, 32]) and np.allclose(v.K[:2, :2], K[:2, :2])
    assert np.allclose(v.T_cam_from_world.t, -T_wc.t)
    edge = np.zeros(SHAPE, bool)
    edge[0:3, 0:2] = True
    assert TrackView.crop(K, T_wc, edge, depth, 1.0).mask.shape == (14, 13)
    assert TrackView.crop(K, T_wc, np.zeros(SHAPE, bool), depth, 1.0) is None
    # a track keeps at most max_views of its views, a uniform sample of them
    counts = np.zeros(10)
    for seed in range(200):
        pts = TrackPoints(RefitConfig(max_views=3, seed=seed))
        for k in range(10):
            pts.add(0, np.zeros((0, 3)), T_wc, TrackView(K, T_wc.inverse(), mask, np.full(SHAPE, float(k))))
        kept = [int(view.depth_m[0, 0]) for view in pts.views(0)]
        assert len(kept) == len(set(kept)) == 3
        counts[kept] += 1
    assert counts.min() > 0.5 * counts.mean()  # the late views as likely as the first ones


def test_the_view_picks_the_model_the_frames_do_not_see_through(stab_model: CadModel, stab: ModelGeometry) -> None:
    """The points of a part fit a longer decoy (the part plus a bar) as well as the part; only the views show that
    the bar is not there (the wall behind is seen where it would be)."""
    decoy = ModelGeometry.from_cad(_with_handle(stab_model), 3000)
    pts = _views(stab, T_WO, n=4)
    P, views = pts.of(0)[0], pts.views(0)
    assert len(views) == 4
    geoms, fits = {6: stab, 12: decoy}, {6: T_WO, 12: T_WO}
    assert depth_fit(decoy, T_WO, P) <= depth_fit(stab, T_WO, P) + 1e-4
    # by the points the decoy, the track's model, stays
    assert pick_model(fits, geoms, P, own=12, margin=0.1) == 12
    # by the views the part wins, from either
    assert pick_model(fits, geoms, P, own=12, margin=0.1, views=views, tol_rel=0.05, band_px=1.5) == 6
    assert pick_model(fits, geoms, P, own=6, margin=0.1, views=views, tol_rel=0.05, band_px=1.5) == 6
    # unless the views' difference is within min_px per view
    own_px = view_score(decoy, T_WO, views, ViewScoring(0.05 * decoy.diameter_m, 1.5, decoy.diameter_m))
    assert own_px > 4 * 20
    for min_px, want in ((0.25 * own_px / 4, 6), (own_px / 4, 12)):
        assert pick_model(fits, geoms, P, own=12, margin=0.1, views=views, tol_rel=0.05, band_px=1.5,
                          min_px=min_px) == want
    # a model fitted far off disagrees everywhere
    off = Rigid3(T_WO.R, T_WO.t + np.array([0.0, 0.0, 0.5]))
    assert pick_model({6: off, 12: T_WO}, geoms, P, own=6, margin=0.1, views=views) == 12
    with pytest.raises(ValueError, match="at least one"):
        pick_model({}, geoms, P, own=6, margin=0.1)


def test_a_turn_the_points_cannot_see_is_decided_by_the_views() -> None:
    """A rod with a thin fin: the points (on the rod only) fit any roll about its axis alike; the views show the
    fin, and the roll is turned back from 20 deg to what they resolve (the fin's tip moves ~1 px per 8 deg, and
    disagreement within 1.5 px of an outline is not counted)."""
    import trimesh

    rod = trimesh.creation.cylinder(radius=0.03, height=0.5, sections=48)
    rod.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0]))  # along x
    fin = trimesh.creation.box(extents=(0.3, 0.04, 0.2))  # through the rod: the centroid stays on its axis
    part = trimesh.util.concatenate([rod, fin])
    geom = ModelGeometry.from_cad(CadModel("finned", np.asarray(part.vertices), np.asarray(part.faces)), 4000)
    rng = np.random.default_rng(0)
    a, x = rng.uniform(0, 2 * math.pi, 1500), rng.uniform(-0.24, 0.24, 1500)
    P = T_WO.apply(np.stack([x, 0.03 * np.cos(a), 0.03 * np.sin(a)], 1))  # the rod's surface, not its samples
    views = [_view(geom, T_WO, T_wc) for T_wc in _cameras(geom, T_WO, 5)]
    c = geom.samples.mean(0)

    def rolled(deg: float) -> Rigid3:
        R = T_WO.R @ axis_angle_to_matrix(np.array([math.radians(deg), 0.0, 0.0]))
        return Rigid3(R, T_WO.apply(c[None])[0] - R @ c)

    assert abs(depth_fit(geom, rolled(20.0), P) - depth_fit(geom, T_WO, P)) < 1e-3
    T = turn_by_view(geom, rolled(20.0), P, views, (16.0, 8.0, 4.0), ViewScoring(0.01, 1.5, geom.diameter_m), 0.02)
    assert _err(T, T_WO)[1] <= 8.5 and _err(T, T_WO)[0] < 0.01
    # nothing to look at, or no steps: unchanged
    loose = ViewScoring(0.01, 1.5, 1.0)
    assert _err(turn_by_view(geom, rolled(20.0), P, [], (16.0,), loose, 0.02), rolled(20.0))[1] < 1e-6
    assert _err(turn_by_view(geom, rolled(20.0), P, views, (), loose, 0.02), rolled(20.0))[1] < 1e-6
    # each turn fitted again to the points (the rod's axis keeps its place): the same
    C = np.repeat(_cameras(geom, T_WO, 1)[0].t[None], len(P), 0)
    T = turn_by_view(geom, rolled(20.0), P, views, (16.0, 8.0, 4.0), ViewScoring(0.01, 1.5, geom.diameter_m), 0.02,
                     C=C, icp_iters=5)
    assert _err(T, T_WO)[1] <= 8.5 and _err(T, T_WO)[0] < 0.01
    # a gain within min_gain pixels is not taken
    start = view_score(geom, rolled(20.0), views, ViewScoring(0.01, 1.5, geom.diameter_m))
    assert _err(turn_by_view(geom, rolled(20.0), P, views, (16.0, 8.0, 4.0),
                             ViewScoring(0.01, 1.5, geom.diameter_m), 0.02, min_gain=start), rolled(20.0))[1] < 1e-6
    # the true pose stays
    assert _err(turn_by_view(geom, T_WO, P, views, (16.0, 8.0, 4.0), loose, 0.02), T_WO)[1] < 1e-6


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
    # the hops: 12 more coarse starts (3 axes, 2 ways, 2 fractions) around the fused pose and each of the 4 kept
    no_hops = refit_world_pose(stab, start, P, C, RefitConfig(hops=()))
    assert res.starts - no_hops.starts == 5 * 12


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


def test_the_track_its_points_hug_is_kept_over_a_loose_one(stab: ModelGeometry) -> None:
    """A track a little off (0.7 tolerances), its own points loose (noise of half a tolerance: a mask spilling off
    the part), has nearly all of both tracks' points within the tolerance, more than the right track has; the right
    track's points lie on its pose, so its pose is closer to both and it is kept."""
    cfg = RefitConfig()
    tol = cfg.dup_tol * stab.diameter_m
    right = _views(stab, T_WO, n=4).of(0)[0]
    off = Rigid3(T_WO.R, T_WO.t + np.array([0.0, 0.0, 0.7 * tol]))
    loose = _views(stab, off, n=3).of(0)[0]
    loose = loose + np.random.default_rng(0).normal(scale=0.5 * tol / math.sqrt(3), size=loose.shape)
    both = np.concatenate([right, loose])
    assert explained(stab, off, both, tol) > explained(stab, T_WO, both, tol)  # the share would keep the loose one
    assert closeness(stab, T_WO, both, tol) > closeness(stab, off, both, tol)
    for frames in (2, 9):  # visited first or second
        assert duplicates([_fitted(0, stab, T_WO, right, 4), _fitted(1, stab, off, loose, frames)], cfg) == {1: 0}
    # points on the surface are as close as the samples' spacing allows; none within the tolerance, or none: 0
    assert closeness(stab, T_WO, right, tol) > 0.6
    assert closeness(stab, T_WO, right + [0.0, 0.0, 1.0], tol) == 0 == closeness(stab, T_WO, right[:0], tol)


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
    assert 0.0 <= track.fit_rel < 0.05  # its points lie on the model (completion's max_fit_rel reads this)
    pipe.fuser.retire(track.track_id)
    assert [w.track_id for w in pipe.world_tracks()] == [track.track_id]


def test_the_pipeline_refit_chooses_the_model_of_the_class_the_views_agree_with(stab_model: CadModel,
                                                                                stab: ModelGeometry) -> None:
    """A track given the decoy model of its class (the part plus a bar) on its first views: the refit fits both
    models and hands completion the part's model, unless ``choose_model`` is off."""
    decoy = _with_handle(stab_model)
    for choose, want in (("view", 6), ("off", 12)):
        cfg = replace(PRESETS["accurate"], complete=replace(
            PRESETS["accurate"].complete, refit=replace(RefitConfig(), choose_model=choose)))
        pipe = PosePipeline(None, {6: stab_model, 12: decoy}, ("background", "structure", "valve", "hot_stab"), cfg)
        for f, T_wc in enumerate(_cameras(stab, T_WO, 5)):
            obs = [Observation(3, T_wc.inverse() @ T_WO, 12, decoy.symmetry, decoy.diameter_m)]
            fused = pipe.fuser.update(f, obs, T_wc)
            pipe.points.add(fused[0].track_id, _frame_points(stab, T_WO, T_wc), T_wc,
                            _view(stab, T_WO, T_wc) if choose == "view" else None)
        [track] = pipe.world_tracks()
        assert track.obj_id == want
        assert _err(track.T_world_from_obj, T_WO)[0] < 0.01
    no_refit = PosePipeline(None, {6: stab_model}, pipe.class_names, PRESETS["balanced"])
    assert no_refit.points is None and no_refit.world_tracks() == []


def test_the_refit_compares_its_fits_by_the_views_where_the_points_cannot_tell(stab: ModelGeometry) -> None:
    """Points on the middle of the probe only: the probe fits them anywhere along its axis. The views (the whole
    part's mask, its depth before a wall) tell where it is: the fit shifted along the axis shows wall through
    its far end and leaves the near end's mask unexplained."""
    pts = _views(stab, T_WO, n=5)
    P, C = pts.of(0)
    local = T_WO.inverse().apply(P)
    mid = (np.abs(local[:, 1]) < 0.1) & (local[:, 2] < 0.05)
    P, C = P[mid], C[mid]
    T_off = Rigid3(T_WO.R, T_WO.t + T_WO.R @ np.array([0.0, 0.2, 0.0]))  # 0.2 m along the probe
    assert abs(depth_fit(stab, T_off, P) - depth_fit(stab, T_WO, P)) < 1e-3
    scoring = ViewScoring(0.05 * stab.diameter_m, 1.5, stab.diameter_m)
    cfg = RefitConfig(view_pick_rel=1.0, view_pick_max_fit=0.04)
    blind = refit_world_pose(stab, T_off, P, C, cfg)
    seeing = refit_world_pose(stab, T_off, P, C, cfg, None, pts.views(0), scoring)
    assert blind is not None and seeing is not None
    # the fits slide along the axis: the views pick the one nearest the part (measured 0.05 m against 0.13 m)
    far = _err(blind.T_world_from_obj, T_WO)[0]
    assert far > 0.1
    assert _err(seeing.T_world_from_obj, T_WO)[0] < min(0.07, 0.5 * far)
    assert view_score(stab, seeing.T_world_from_obj, pts.views(0), scoring) < view_score(
        stab, blind.T_world_from_obj, pts.views(0), scoring)
    # off (view_pick_rel = 0), or when no fit explains the points within view_pick_max_fit, the views change nothing
    for cfg in (RefitConfig(view_pick_rel=0.0), RefitConfig(view_pick_rel=1.0, view_pick_max_fit=1e-6)):
        off = refit_world_pose(stab, T_off, P, C, cfg, None, pts.views(0), scoring)
        assert off is not None and np.allclose(off.T_world_from_obj.matrix(), blind.T_world_from_obj.matrix())

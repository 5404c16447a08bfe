"""Temporal fusion: no flips between symmetric solutions, robust world mean, constant-velocity filter."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.cad.symmetry import Symmetry, axis_angle_matrix
from cadalign.geometry.rotations import axis_angle_to_matrix, random_rotation
from cadalign.infer.config import TemporalConfig
from cadalign.infer.ego import predict_camera, register_camera
from cadalign.infer.pose_math import Observation, apply_twist_camera, canonicalize, robust_mean, twist_between
from cadalign.infer.temporal import TemporalFuser
from cadalign.metrics.pose import rotation_error_deg
from cadalign.types import Rigid3

Z2 = Symmetry.from_name("discrete_z2")
CONT = Symmetry.continuous([0, 0, 1])


def _noisy(T: Rigid3, rng: np.random.Generator, t_m: float = 0.003, r_deg: float = 0.5) -> Rigid3:
    dR = axis_angle_to_matrix(rng.normal(scale=math.radians(r_deg), size=3))
    return Rigid3(dR @ T.R, T.t + rng.normal(scale=t_m, size=3))


def _flipped(T: Rigid3, sym: Symmetry, k: int, rng: np.random.Generator) -> Rigid3:
    """An equivalent solution ``T S``: the k-th discrete symmetry, or a random spin for a continuous one."""
    if sym.kind == "continuous":
        S = Symmetry.continuous(sym.axis).discretize(360)[int(rng.integers(360))]
    else:
        S = sym.discretize()[k % len(sym.discretize())]
    return Rigid3.from_matrix(T.matrix() @ S)


def _camera_orbit(i: int) -> Rigid3:
    """``T_world_from_cam`` on a circle around the origin, looking at it."""
    a = 0.1 * i
    eye = np.array([3 * math.cos(a), 3 * math.sin(a), 1.0])
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    return Rigid3(np.stack([x, np.cross(z, x), z], axis=1), eye)


@pytest.mark.parametrize("sym", [Z2, CONT], ids=["discrete_z2", "continuous_z"])
@pytest.mark.parametrize("mode", ["world", "filter", "ego"])
def test_fusion_does_not_flip_between_symmetric_solutions(sym: Symmetry, mode: str) -> None:
    rng = np.random.default_rng(0)
    world = mode == "world"
    T_world_from_obj = Rigid3(random_rotation(np.random.default_rng(1)), np.array([0.2, -0.1, 0.3]))
    fuser = TemporalFuser(TemporalConfig(mode="auto" if mode != "filter" else "filter"))
    prev, raw_jumps, fused_jumps = None, [], []
    raw_prev = None
    for i in range(20):
        T_wc = _camera_orbit(i) if world else _camera_orbit(0)
        T_true = T_wc.inverse() @ T_world_from_obj
        meas = _noisy(_flipped(T_true, sym, i, rng), rng)  # every frame a different equivalent solution
        out = fuser.update(i, [Observation(1, meas, 7, sym, 0.5)], T_wc if world else None)
        expect = "filter" if mode == "ego" and sym.kind == "continuous" else mode  # auto without a pose: ego
        assert len(out) == 1 and out[0].track_id == 0 and out[0].mode == expect
        T_out = out[0].T_cam_from_obj
        assert rotation_error_deg(T_out.R, T_true.R, sym) < 2.0  # right up to the symmetry
        T_out_w = T_wc @ T_out
        if prev is not None:
            fused_jumps.append(rotation_error_deg(T_out_w.R, prev.R))  # plain angle: a flip would show
            raw_jumps.append(rotation_error_deg((T_wc @ meas).R, raw_prev.R))
        prev, raw_prev = T_out_w, T_wc @ meas
    assert max(raw_jumps) > 90.0  # the raw sequence does flip ...
    assert max(fused_jumps) < 2.0  # ... the fused one does not


def test_canonicalize_returns_the_closest_equivalent() -> None:
    T = Rigid3(random_rotation(np.random.default_rng(3)), np.array([1.0, 2, 3]))
    flipped = Rigid3.from_matrix(T.matrix() @ Z2.discrete[0])
    back = canonicalize(flipped, Z2, T.R)
    np.testing.assert_allclose(back.matrix(), T.matrix(), atol=1e-12)
    spun = Rigid3.from_matrix(T.matrix() @ CONT.discretize(8)[3])
    np.testing.assert_allclose(canonicalize(spun, CONT, T.R).matrix(), T.matrix(), atol=1e-9)
    assert canonicalize(T, None, np.eye(3)) is T


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), angle=st.floats(-math.pi, math.pi))
def test_canonicalize_continuous_is_optimal(seed: int, angle: float) -> None:
    rng = np.random.default_rng(seed)
    T = Rigid3(random_rotation(rng), rng.normal(size=3))
    R_ref = random_rotation(rng)
    best = canonicalize(T, CONT, R_ref)
    S = np.eye(4)
    S[:3, :3] = axis_angle_matrix(np.array([0, 0, 1.0]), angle)
    other = Rigid3.from_matrix(T.matrix() @ S)
    assert rotation_error_deg(best.R, R_ref) <= rotation_error_deg(other.R, R_ref) + 1e-6
    assert rotation_error_deg(best.R, T.R, CONT) < 1e-5  # still the same physical pose


def test_robust_mean_resists_an_outlier() -> None:
    rng = np.random.default_rng(0)
    poses = [_noisy(Rigid3(), rng, 0.002, 0.3) for _ in range(9)] + [Rigid3(axis_angle_to_matrix([0, 0, 1.0]),
                                                                          [1.0, 0, 0])]
    m = robust_mean(poses, 0.05, math.radians(5))
    assert np.linalg.norm(m.t) < 0.01
    assert rotation_error_deg(m.R, np.eye(3)) < 1.0


def test_twist_roundtrip() -> None:
    rng = np.random.default_rng(4)
    A = Rigid3(random_rotation(rng), rng.normal(size=3))
    B = Rigid3(random_rotation(rng), rng.normal(size=3))
    np.testing.assert_allclose(apply_twist_camera(twist_between(A, B), A).matrix(), B.matrix(), atol=1e-9)


def test_filter_tracks_constant_velocity_and_rejects_an_outlier() -> None:
    xi = np.array([0.0, 0.02, 0.0, 0.05, 0.0, 0.0])  # the part drifts and turns in the camera frame
    T = Rigid3(np.eye(3), np.array([0.0, 0.0, 3.0]))
    fuser = TemporalFuser(TemporalConfig(mode="filter"))
    for i in range(15):
        meas = T
        if i == 10:  # a wild detection: turned by 60 degrees (beyond the 30 degree gate)
            meas = Rigid3(axis_angle_to_matrix([math.radians(60), 0, 0]) @ T.R, T.t)
        out = fuser.update(i, [Observation(1, meas, 3, Symmetry.none(), 0.5)])[0]
        if i >= 8:
            assert np.linalg.norm(out.T_cam_from_obj.t - T.t) < 0.02
            assert rotation_error_deg(out.T_cam_from_obj.R, T.R) < 1.0
        T = apply_twist_camera(xi, T)
    assert len(fuser.tracks) == 1


def test_two_parts_get_two_tracks_and_none_mode_passes_through() -> None:
    fuser = TemporalFuser(TemporalConfig())
    A = Rigid3(np.eye(3), np.array([0.0, 0.0, 3.0]))
    B = Rigid3(np.eye(3), np.array([1.5, 0.0, 3.0]))
    for i in range(3):
        out = fuser.update(i, [Observation(1, B, 3, Symmetry.none(), 0.5), Observation(1, A, 3, Symmetry.none(), 0.5)])
        assert [o.track_id for o in out] == [0, 1]
    raw = TemporalFuser(TemporalConfig(mode="none")).update(0, [Observation(1, A)])
    assert raw[0].T_cam_from_obj is A and raw[0].track_id == -1


def test_tracks_in_view_need_an_established_track() -> None:
    fuser = TemporalFuser(TemporalConfig())
    T = Rigid3(np.eye(3), np.array([0.0, 0.0, 3.0]))
    for i in range(3):
        assert fuser.tracks_in_view(2, i) == []  # fewer than three observations so far
        fuser.update(i, [Observation(2, T, 5, Symmetry.none(), 0.5)])
    (oid, T_pred), = fuser.tracks_in_view(2, 3)
    assert oid == 5 and np.allclose(T_pred.matrix(), T.matrix())
    assert fuser.tracks_in_view(3, 3) == []  # another class
    assert TemporalFuser(TemporalConfig(mode="none")).tracks_in_view(2, 3) == []


def test_a_track_keeps_the_largest_identification_mask_and_a_retired_one_is_gone() -> None:
    fuser = TemporalFuser(TemporalConfig())
    T = Rigid3(np.eye(3), np.array([0.0, 0.0, 3.0]))
    for i, px in enumerate((40, 0, 0)):  # identified on frame 0's 40 px mask; later frames carried the model
        fuser.update(i, [Observation(2, T, 5, Symmetry.none(), 0.5, px)])
    (tid, oid, _, id_px), = fuser.track_views(2, 3)
    assert (tid, oid, id_px) == (0, 5, 40)
    fuser.note_identified(tid, 90)
    fuser.note_identified(tid, 60)
    assert fuser.track_views(2, 3)[0][3] == 90
    fuser.retire(tid)
    assert fuser.track_views(2, 3) == [] and fuser.tracks_in_view(2, 3) == []
    out = fuser.update(3, [Observation(2, T, 7, Symmetry.none(), 0.5, 120)])  # another model at the same place
    assert out[0].track_id == 1 and out[0].n_obs == 1


def _panel(rng: np.random.Generator, n: int = 5) -> list[Rigid3]:
    """``n`` static parts (world-from-obj) spread over a 2 m panel around the origin."""
    return [Rigid3(random_rotation(rng), np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-0.3, 0.3)]))
            for _ in range(n)]


def _far_orbit(i: int) -> Rigid3:
    """``T_world_from_cam`` on a circle of radius 10 m (the default orbit's distance), 2 deg per frame."""
    a = math.radians(2.0 * i)
    eye = np.array([10 * math.cos(a), 10 * math.sin(a), 2.0])
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    return Rigid3(np.stack([x, np.cross(z, x), z], axis=1), eye)


def _fused_errors(mode: str, frames: int = 16) -> tuple[float, float, TemporalFuser, list[str]]:
    """Worst fused translation (m) and rotation (deg) error over the last 8 frames of a 10 m orbit around five
    static parts seen without camera poses: 2 mm / 0.3 deg noise, one part flipped by 180 deg in frames 5-7."""
    rng = np.random.default_rng(4)
    parts = _panel(rng)
    fuser = TemporalFuser(TemporalConfig(mode=mode))
    worst_t, worst_r, modes = 0.0, 0.0, []
    flip = axis_angle_to_matrix(np.array([0.0, math.pi, 0.0]))
    for i in range(frames):
        C = _far_orbit(i)
        truth = [C.inverse() @ P for P in parts]
        obs = []
        for k, T in enumerate(truth):
            meas = _noisy(T, rng, 0.002, 0.3)
            if k == 2 and 5 <= i <= 7:
                meas = Rigid3(meas.R @ flip, meas.t)
            obs.append(Observation(1, meas, 10 + k, Symmetry.none(), 0.6))
        out = fuser.update(i, obs)
        modes += [o.mode for o in out]
        if i >= frames - 8:
            pairs = list(zip(out, truth, strict=True))
            worst_t = max(worst_t, *[float(np.linalg.norm(o.T_cam_from_obj.t - T.t)) for o, T in pairs])
            worst_r = max(worst_r, *[rotation_error_deg(o.T_cam_from_obj.R, T.R) for o, T in pairs])
    return worst_t, worst_r, fuser, modes


def test_ego_fuses_static_parts_without_camera_poses_and_the_filter_lags() -> None:
    t_ego, r_ego, fuser, modes = _fused_errors("auto")
    assert set(modes) == {"ego"} and len(fuser.tracks) == 5  # the flipped part kept its track
    assert t_ego < 0.01 and r_ego < 1.0
    t_f, r_f, _, _ = _fused_errors("filter")
    assert t_f > 3 * t_ego  # each part's filter learns the camera's motion on its own, and lags it


def test_register_camera_recovers_the_camera_and_rejects_a_misplaced_part() -> None:
    rng = np.random.default_rng(7)
    parts = _panel(rng, 4)
    C = _far_orbit(3)
    obs = [Observation(1, C.inverse() @ P, 0, Z2, 0.6) for P in parts]
    obs[1] = Observation(1, Rigid3(obs[1].T_cam_from_obj.R, obs[1].T_cam_from_obj.t + [0.5, 0.0, 0.0]), 0, Z2, 0.6)
    obs[3] = Observation(1, Rigid3.from_matrix(obs[3].T_cam_from_obj.matrix() @ Z2.discrete[0]), 0, Z2, 0.6)
    cands = [list(range(4))] * 4
    est, inliers = register_camera(obs, cands, parts, [0.3] * 4, 0.05, math.radians(5), None)
    assert sorted(inliers) == [0, 2, 3]  # the half-turned equivalent of part 3 is as good as part 3
    np.testing.assert_allclose(est.matrix(), C.matrix(), atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 4), layout=st.sampled_from(["spread", "collinear", "same"]))
def test_register_camera_is_exact_on_degenerate_layouts(seed: int, n: int, layout: str) -> None:
    rng = np.random.default_rng(seed)
    parts = _panel(rng, n)
    if layout != "spread":  # parts on one line, or all at one point: the positions do not fix the rotation
        step = np.array([0.3, 0.1, 0.0]) if layout == "collinear" else np.zeros(3)
        parts = [Rigid3(P.R, k * step) for k, P in enumerate(parts)]
    C = Rigid3(random_rotation(rng), rng.normal(scale=20.0, size=3))
    obs = [Observation(1, C.inverse() @ P, k) for k, P in enumerate(parts)]
    est, inliers = register_camera(obs, [[k] for k in range(n)], parts, [0.3] * n, 0.05, math.radians(5), None)
    assert sorted(inliers) == list(range(n))
    np.testing.assert_allclose(est.matrix(), C.matrix(), atol=1e-7)


def test_register_camera_without_a_known_part_gives_none() -> None:
    obs = [Observation(1, Rigid3(np.eye(3), np.array([0.0, 0.0, 5.0])), 3)]
    assert register_camera(obs, [[]], [], [0.3], 0.05, 0.1, None) == (None, [])
    assert predict_camera([], 3) is None


def test_ego_bridges_a_frame_without_known_parts_then_starts_a_new_world() -> None:
    rng = np.random.default_rng(2)
    parts = _panel(rng, 3)
    fuser = TemporalFuser(TemporalConfig(mode="ego", max_missed=2))
    for i in range(4):
        fuser.update(i, [Observation(1, _far_orbit(i).inverse() @ P, k) for k, P in enumerate(parts)])
    new = Rigid3(np.eye(3), np.array([0.0, 0.0, 4.0]))
    out = fuser.update(4, [Observation(2, new, 9)])  # a part never seen: the camera is predicted
    expect = _far_orbit(0).inverse() @ _far_orbit(4)  # the orbit's constant motion, in the world of frame 0
    np.testing.assert_allclose(fuser._ego[-1][1].matrix(), expect.matrix(), atol=1e-6)
    assert out[0].mode == "ego" and np.allclose(out[0].T_cam_from_obj.matrix(), new.matrix())
    other = Rigid3(np.eye(3), np.array([1.0, 0.0, 6.0]))
    for i in (8, 9):  # beyond max_missed frames with nothing known: a new world, the old tracks retire
        out = fuser.update(i, [Observation(3, other, 11)])
    assert out[0].mode == "ego" and np.allclose(out[0].T_cam_from_obj.matrix(), other.matrix())
    assert {tr.space for tr in fuser.tracks} == {"retired", "ego"}
    # the camera of every registered frame, in the world it was registered in (for track completion)
    assert {i: w for i, (w, _) in fuser.cameras.items()} == {0: 1, 1: 1, 2: 1, 3: 1, 4: 1, 8: 2, 9: 2}
    np.testing.assert_allclose(fuser.cameras[4][1].matrix(), expect.matrix(), atol=1e-6)
    assert [tr.world for tr in fuser.tracks] == [1, 1, 1, 1, 2]


def test_world_mode_keeps_the_given_cameras_in_world_0() -> None:
    fuser = TemporalFuser(TemporalConfig())
    P = Rigid3(np.eye(3), np.array([0.2, 0.0, 0.5]))  # a static part, world-from-obj
    for i in range(3):
        fuser.update(i, [Observation(1, _far_orbit(i).inverse() @ P, 7)] if i != 1 else [], _far_orbit(i))
    assert sorted(fuser.cameras) == [0, 1, 2] and all(w == 0 for w, _ in fuser.cameras.values())
    np.testing.assert_allclose(fuser.cameras[1][1].matrix(), _far_orbit(1).matrix())
    assert [tr.world for tr in fuser.tracks] == [0]


def test_ego_leaves_parts_with_a_continuous_symmetry_alone_to_the_filter() -> None:
    fuser = TemporalFuser(TemporalConfig(mode="ego"))
    T = Rigid3(np.eye(3), np.array([0.0, 0.0, 3.0]))
    for i in range(3):  # such a part cannot fix the camera's turn about its axis
        out = fuser.update(i, [Observation(1, T, 4, CONT, 0.5)])
        assert out[0].mode == "filter"
    out = fuser.update(3, [Observation(1, T, 4, CONT, 0.5), Observation(2, T, 5, Z2, 0.5)])
    assert [o.mode for o in out] == ["ego", "ego"]  # a part that can joins it to an ego world

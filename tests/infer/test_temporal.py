"""Temporal fusion: no flips between symmetric solutions, robust world mean, constant-velocity filter."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.cad.symmetry import Symmetry, axis_angle_matrix
from cadalign.eval.pose_metrics import rotation_error_deg
from cadalign.geometry.rotations import axis_angle_to_matrix, random_rotation
from cadalign.infer.temporal import (
    Observation,
    TemporalConfig,
    TemporalFuser,
    _apply_twist,
    canonicalize,
    robust_mean,
    twist_between,
)
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
@pytest.mark.parametrize("world", [True, False], ids=["world", "filter"])
def test_fusion_does_not_flip_between_symmetric_solutions(sym: Symmetry, world: bool) -> None:
    rng = np.random.default_rng(0)
    T_world_from_obj = Rigid3(random_rotation(np.random.default_rng(1)), np.array([0.2, -0.1, 0.3]))
    fuser = TemporalFuser(TemporalConfig())
    prev, raw_jumps, fused_jumps = None, [], []
    raw_prev = None
    for i in range(20):
        T_wc = _camera_orbit(i) if world else _camera_orbit(0)
        T_true = T_wc.inverse() @ T_world_from_obj
        meas = _noisy(_flipped(T_true, sym, i, rng), rng)  # every frame a different equivalent solution
        out = fuser.update(i, [Observation(1, meas, 7, sym, 0.5)], T_wc if world else None)
        assert len(out) == 1 and out[0].track_id == 0 and out[0].mode == ("world" if world else "filter")
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
    np.testing.assert_allclose(_apply_twist(twist_between(A, B), A).matrix(), B.matrix(), atol=1e-9)


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
        T = _apply_twist(xi, T)
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


def test_known_model_needs_an_established_track() -> None:
    fuser = TemporalFuser(TemporalConfig())
    T = Rigid3(np.eye(3), np.array([0.0, 0.0, 3.0]))
    near = Rigid3(np.eye(3), np.array([0.02, 0.0, 3.0]))
    for i in range(3):
        assert fuser.known_model(2, near, i, 0.05) is None  # fewer than three observations so far
        fuser.update(i, [Observation(2, T, 5, Symmetry.none(), 0.5)])
    assert fuser.known_model(2, near, 3, 0.05) == 5
    assert fuser.known_model(2, Rigid3(np.eye(3), np.array([0.2, 0.0, 3.0])), 3, 0.05) is None  # beyond the gate
    assert fuser.known_model(3, near, 3, 0.05) is None  # another class

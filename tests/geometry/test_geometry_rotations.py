"""Rotation conversions and distances: round trips, extremes, degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_testdata import DETERMINISTIC
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry import (
    axis_angle_to_matrix,
    geodesic_angle,
    is_rotation,
    matrix_to_axis_angle,
    matrix_to_quaternion,
    matrix_to_rotation_6d,
    orthonormalize,
    quaternion_angle,
    quaternion_canonicalize,
    quaternion_normalize,
    quaternion_to_matrix,
    random_rotation,
    rotation_6d_to_matrix,
)

SPECIAL_ANGLES = [0.0, 1e-12, 1e-9, 1e-6, 1e-3, 0.5, np.pi / 2, np.pi - 1e-3, np.pi - 1e-7, np.pi - 1e-9, np.pi]

unit_axes = (
    st.lists(st.floats(-1, 1, allow_nan=False), min_size=3, max_size=3)
    .map(np.array)
    .filter(lambda v: np.linalg.norm(v) > 1e-3)
    .map(lambda v: v / np.linalg.norm(v))
)
angles = st.sampled_from(SPECIAL_ANGLES) | st.floats(0.0, np.pi)
rotvecs = st.builds(lambda axis, angle: axis * angle, unit_axes, angles)


def _rotation_error(R1: np.ndarray, R2: np.ndarray) -> float:
    return float(np.max(geodesic_angle(R1, R2)))


@settings(max_examples=60, **DETERMINISTIC)
@given(rotvecs)
def test_roundtrip_matrix_quaternion_axis_angle_6d(rotvec: np.ndarray) -> None:
    R = axis_angle_to_matrix(rotvec)
    assert is_rotation(R, tol=1e-12)
    q = matrix_to_quaternion(R)
    assert abs(np.linalg.norm(q) - 1) < 1e-15 and q[0] >= 0
    assert _rotation_error(quaternion_to_matrix(q), R) < 1e-14
    rv = matrix_to_axis_angle(R)
    assert np.linalg.norm(rv) <= np.pi + 1e-15
    assert _rotation_error(axis_angle_to_matrix(rv), R) < 1e-14
    if np.linalg.norm(rotvec) < np.pi - 1e-6:  # the rotation vector itself is unique below pi
        assert np.allclose(rv, rotvec, rtol=1e-12, atol=1e-15)
    assert _rotation_error(rotation_6d_to_matrix(matrix_to_rotation_6d(R)), R) < 1e-14
    assert np.array_equal(quaternion_canonicalize(-q), q)


@settings(max_examples=30, **DETERMINISTIC)
@given(st.integers(0, 2**32 - 1))
def test_batched_conversions_match_single(seed: int) -> None:
    R = random_rotation(np.random.default_rng(seed), 5).reshape(5, 1, 3, 3)
    q = matrix_to_quaternion(R)
    assert q.shape == (5, 1, 4)
    for i in range(5):
        assert np.array_equal(q[i, 0], matrix_to_quaternion(R[i, 0]))
    assert matrix_to_axis_angle(R).shape == (5, 1, 3)
    assert rotation_6d_to_matrix(matrix_to_rotation_6d(R)).shape == (5, 1, 3, 3)


@pytest.mark.parametrize("angle", [1e-9, 1e-6, 1e-3, np.pi - 1e-7, np.pi - 1e-9, np.pi])
def test_geodesic_angle_extremes(angle: float) -> None:
    rng = np.random.default_rng(7)
    for _ in range(20):
        R1 = random_rotation(rng)
        axis = rng.standard_normal(3)
        axis /= np.linalg.norm(axis)
        R2 = R1 @ axis_angle_to_matrix(angle * axis)
        assert abs(geodesic_angle(R1, R2) - angle) < 1e-7
        assert abs(geodesic_angle(R1, R2) - angle) < 1e-12  # what the atan2 form actually achieves
        q1, q2 = matrix_to_quaternion(R1), matrix_to_quaternion(R2)
        assert abs(quaternion_angle(q1, q2) - angle) < 1e-12


def test_axis_angle_near_pi_recovers_axis() -> None:
    axis = np.array([0.3, -0.5, 0.81])
    axis /= np.linalg.norm(axis)
    for eps in [1e-3, 1e-7, 1e-10, 0.0]:
        rv = matrix_to_axis_angle(axis_angle_to_matrix((np.pi - eps) * axis))
        sign = np.sign(rv @ axis)  # at exactly pi either sign is the same rotation
        assert np.allclose(sign * rv, (np.pi - eps) * axis, atol=1e-12)


def test_axis_angle_tiny_angles_are_exact() -> None:
    for t in [0.0, 1e-300, 1e-20, 1e-9, 1e-5, 2e-4]:
        rv = t * np.array([0.0, 0.6, 0.8])
        assert np.allclose(matrix_to_axis_angle(axis_angle_to_matrix(rv)), rv, rtol=1e-12, atol=1e-300)


def test_quaternion_sign_tie_break_at_w_zero() -> None:
    q = np.array([0.0, -1.0, 0.0, 0.0])
    assert np.array_equal(quaternion_canonicalize(q), [0.0, 1.0, 0.0, 0.0])
    q = np.array([0.0, 0.0, -0.6, 0.8])
    assert np.array_equal(quaternion_canonicalize(q), [0.0, 0.0, 0.6, -0.8])
    R = quaternion_to_matrix(np.array([0.0, 0.0, -0.6, 0.8]))
    assert np.allclose(matrix_to_quaternion(R), [0.0, 0.0, 0.6, -0.8], atol=1e-15)


def test_zero_quaternion_raises() -> None:
    with pytest.raises(DegenerateGeometryError):
        quaternion_normalize(np.zeros(4))
    with pytest.raises(DegenerateGeometryError):
        quaternion_to_matrix(np.array([[1.0, 0, 0, 0], [0, 0, 0, 0]]))


@pytest.mark.parametrize(
    "d6",
    [
        [1, 0, 0, 1, 1e-9, 0],  # near-parallel
        [1, 0, 0, -2, 0, 1e-8],  # near-antiparallel
        [1, 2, 3, 2, 4, 6],  # exactly parallel
        [0, 0, 0, 0, 1, 0],  # zero first column
        [1, 0, 0, 0, 0, 0],  # zero second column
    ],
)
def test_6d_degenerate_raises(d6: list[float]) -> None:
    with pytest.raises(DegenerateGeometryError):
        rotation_6d_to_matrix(np.array(d6, dtype=float))


def test_6d_accepts_unnormalised_and_rejects_nan() -> None:
    R = rotation_6d_to_matrix(np.array([2.0, 0, 0, 5.0, 3.0, 0]))
    assert np.allclose(R, np.eye(3))
    assert is_rotation(rotation_6d_to_matrix(np.array([1, 0, 0, 1, 1e-5, 0.0])), tol=1e-12)
    with pytest.raises(InputError):
        rotation_6d_to_matrix(np.array([np.nan, 0, 0, 0, 1, 0]))


def test_orthonormalize_fixes_noise_and_reflection() -> None:
    rng = np.random.default_rng(3)
    R = random_rotation(rng, 10)
    noisy = R + 1e-6 * rng.standard_normal(R.shape)
    assert np.all(is_rotation(orthonormalize(noisy), tol=1e-12))
    assert _rotation_error(orthonormalize(noisy), R) < 1e-5
    reflection = np.diag([1.0, 1.0, -1.0])
    assert is_rotation(orthonormalize(reflection), tol=1e-12)


def test_is_rotation_rejects() -> None:
    assert not is_rotation(np.diag([1.0, 1.0, -1.0]))
    assert not is_rotation(2 * np.eye(3))
    assert not is_rotation(np.full((3, 3), np.nan))
    assert is_rotation(np.eye(3))


def test_random_rotation_shapes_and_determinism() -> None:
    a = random_rotation(np.random.default_rng(1), 4)
    b = random_rotation(np.random.default_rng(1), 4)
    assert a.shape == (4, 3, 3) and np.array_equal(a, b)
    assert random_rotation(np.random.default_rng(1)).shape == (3, 3)
    assert np.all(is_rotation(a, tol=1e-12))


def test_shape_errors() -> None:
    with pytest.raises(InputError):
        matrix_to_quaternion(np.eye(4))
    with pytest.raises(InputError):
        axis_angle_to_matrix(np.zeros(4))

"""Euler angles: all 24 sequences, scipy parity, gimbal lock, and the full representation round trip."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_testdata import ALL_EULER_SEQS, DETERMINISTIC, rotation_error, seeds
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from cadalign.errors import InputError
from cadalign.geometry import (
    axis_angle_to_matrix,
    euler_to_matrix,
    matrix_to_axis_angle,
    matrix_to_euler,
    matrix_to_quaternion,
    matrix_to_rotation_6d,
    quaternion_to_matrix,
    random_rotation,
    rotation_6d_to_matrix,
)
from cadalign.geometry.euler import GIMBAL_TOL

angles = st.floats(-np.pi, np.pi)
LOCK_TOL = 1e-9
"""Acceptance criterion for the matrix round trip at gimbal lock (rad)."""


def _is_proper(seq: str) -> bool:
    return seq[0].lower() == seq[2].lower()


def _lock_angles(seq: str) -> list[float]:
    """Middle angles at gimbal lock: +-90 deg for Tait-Bryan, 0 and 180 deg for proper Euler."""
    return [0.0, np.pi] if _is_proper(seq) else [np.pi / 2, -np.pi / 2]


def _wrap(a: np.ndarray) -> np.ndarray:
    """Angle differences wrapped to (-pi, pi]."""
    return np.angle(np.exp(1j * a))


@pytest.mark.parametrize("seq", ALL_EULER_SEQS)
def test_euler_to_matrix_matches_scipy(seq: str) -> None:
    rng = np.random.default_rng(sum(map(ord, seq)))
    ang = rng.uniform(-2 * np.pi, 2 * np.pi, (64, 3))  # beyond the canonical ranges on purpose
    assert np.allclose(euler_to_matrix(ang, seq), Rotation.from_euler(seq, ang).as_matrix(), atol=1e-14)


@pytest.mark.parametrize("seq", ALL_EULER_SEQS)
def test_matrix_to_euler_matches_scipy_away_from_lock(seq: str) -> None:
    rng = np.random.default_rng(sum(map(ord, seq)) + 1)
    R = random_rotation(rng, 256)
    ours = matrix_to_euler(R, seq)
    ref = Rotation.from_matrix(R).as_euler(seq)
    assert np.max(np.abs(_wrap(ours - ref))) < 1e-9
    b = ours[:, 1]
    if _is_proper(seq):
        assert np.all((b >= 0) & (b <= np.pi))
    else:
        assert np.all(np.abs(b) <= np.pi / 2)
    assert np.all(np.abs(ours[:, [0, 2]]) <= np.pi)


@settings(max_examples=25, **DETERMINISTIC)
@given(seeds)
def test_matrix_euler_matrix_round_trip_all_sequences(seed: int) -> None:
    R = random_rotation(np.random.default_rng(seed), 8)
    for seq in ALL_EULER_SEQS:
        assert rotation_error(euler_to_matrix(matrix_to_euler(R, seq), seq), R) < 1e-14


@settings(max_examples=25, **DETERMINISTIC)
@given(angles, angles, st.sampled_from(ALL_EULER_SEQS), st.integers(0, 1))
def test_gimbal_lock_round_trip(a: float, c: float, seq: str, which: int) -> None:
    """At exact lock only a +- c is defined: compare matrices, not angles; the third angle is exactly 0."""
    b = _lock_angles(seq)[which]
    R = euler_to_matrix(np.array([a, b, c]), seq)
    e = matrix_to_euler(R, seq)
    assert rotation_error(euler_to_matrix(e, seq), R) < LOCK_TOL
    assert rotation_error(euler_to_matrix(e, seq), R) < 1e-14  # what it actually achieves at exact lock
    assert e[2] == 0.0
    assert abs(e[1] - b) < 1e-7  # b itself is still determined


@pytest.mark.parametrize("seq", ALL_EULER_SEQS)
def test_near_gimbal_lock_sweep(seq: str) -> None:
    """Just off the lock the split between a and c is ill-conditioned; the matrix must stay exact."""
    rng = np.random.default_rng(sum(map(ord, seq)) + 2)
    deltas = np.array([0.0, 1e-16, 1e-14, 1e-13, 1e-12, 2e-12, 1e-11, 1e-10, 1e-9, 1e-8, 1e-6, 1e-3])
    worst = 0.0
    for b0 in _lock_angles(seq):
        for sign in (1.0, -1.0):
            ang = rng.uniform(-np.pi, np.pi, (deltas.size, 3))
            ang[:, 1] = b0 + sign * deltas
            R = euler_to_matrix(ang, seq)
            worst = max(worst, rotation_error(euler_to_matrix(matrix_to_euler(R, seq), seq), R))
    assert worst < LOCK_TOL
    assert worst <= 2 * GIMBAL_TOL + 1e-14  # the documented bound


def test_gimbal_lock_from_other_representations() -> None:
    """A lock reached through quaternions (rounded differently) is still detected and exact."""
    R = quaternion_to_matrix(np.array([np.sqrt(0.5), 0.0, np.sqrt(0.5), 0.0]))  # 90 deg about y
    for seq in ("xyz", "XYZ", "zyx", "ZYX"):
        e = matrix_to_euler(R, seq)
        assert abs(abs(e[1]) - np.pi / 2) < 1e-7 and e[2] == 0.0
        assert rotation_error(euler_to_matrix(e, seq), R) < 1e-14
    for seq in ("zxz", "ZXZ", "xyx", "YZY"):
        e = matrix_to_euler(np.eye(3), seq)
        assert np.array_equal(e, [0.0, 0.0, 0.0])


@settings(max_examples=30, **DETERMINISTIC)
@given(seeds, st.sampled_from(ALL_EULER_SEQS), st.booleans())
def test_full_representation_chain(seed: int, seq: str, locked: bool) -> None:
    """matrix -> quaternion -> matrix -> axis-angle -> matrix -> 6D -> matrix -> Euler -> matrix."""
    rng = np.random.default_rng(seed)
    if locked:
        R0 = euler_to_matrix(np.array([rng.uniform(-np.pi, np.pi), _lock_angles(seq)[0], 0.3]), seq)
    else:
        R0 = random_rotation(rng)
    R1 = quaternion_to_matrix(matrix_to_quaternion(R0))
    R2 = axis_angle_to_matrix(matrix_to_axis_angle(R1))
    R3 = rotation_6d_to_matrix(matrix_to_rotation_6d(R2))
    R4 = euler_to_matrix(matrix_to_euler(R3, seq), seq)
    for R in (R1, R2, R3, R4):
        assert rotation_error(R, R0) < 1e-13
    back = euler_to_matrix(matrix_to_euler(R0, seq), seq)
    assert np.allclose(matrix_to_quaternion(back), matrix_to_quaternion(R0), atol=1e-13)


@pytest.mark.parametrize("seq", ["xxy", "xYz", "abc", "xy", "xyzx", "XXZ", 3])
def test_invalid_sequences_raise(seq: object) -> None:
    with pytest.raises(InputError):
        euler_to_matrix(np.zeros(3), seq)  # type: ignore[arg-type]
    with pytest.raises(InputError):
        matrix_to_euler(np.eye(3), seq)  # type: ignore[arg-type]


def test_euler_shape_errors_and_batches() -> None:
    with pytest.raises(InputError):
        euler_to_matrix(np.zeros(2), "xyz")
    with pytest.raises(InputError):
        matrix_to_euler(np.eye(4), "xyz")
    ang = np.random.default_rng(0).uniform(-1, 1, (2, 5, 3))
    R = euler_to_matrix(ang, "ZYX")
    assert R.shape == (2, 5, 3, 3)
    assert np.allclose(matrix_to_euler(R, "ZYX"), ang, atol=1e-14)

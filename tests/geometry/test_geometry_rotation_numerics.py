"""Rotation numerics: geodesic accuracy at 0 and pi, nearest rotation, quaternion signs, NaN rows, batching."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from geometry_testdata import DETERMINISTIC, nearest_rotation_horn, rot_about, rotation_error, seeds, unit_vectors
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.errors import InputError
from cadalign.geometry import (
    axis_angle_to_matrix,
    euler_to_matrix,
    geodesic_angle,
    is_rotation,
    matrix_to_axis_angle,
    matrix_to_euler,
    matrix_to_quaternion,
    matrix_to_rotation_6d,
    orthonormalize,
    quaternion_angle,
    quaternion_canonicalize,
    quaternion_multiply,
    quaternion_normalize,
    quaternion_to_matrix,
    random_rotation,
    rotation_6d_to_matrix,
    skew,
)

SMALL = [1e-8, 3e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3]
"""Angles (rad) where ``arccos((trace - 1) / 2)`` loses ~1e-8 rad; the atan2 form must not."""

NEAR_PI = [np.pi - a for a in SMALL] + [np.pi]


# --- geodesic angle ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("angle", [0.0, *SMALL, *NEAR_PI])
def test_geodesic_angle_about_coordinate_axis_is_exact(angle: float) -> None:
    """Rz(angle) has entries cos/sin rounded once, so the true angle is known to ~1e-16."""
    c, s = np.cos(angle), np.sin(angle)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    assert abs(geodesic_angle(np.eye(3), Rz) - angle) < 1e-15
    assert abs(geodesic_angle(Rz, np.eye(3)) - angle) < 1e-15


@settings(max_examples=40, **DETERMINISTIC)
@given(seeds, unit_vectors, st.sampled_from(SMALL + NEAR_PI))
def test_geodesic_angle_near_0_and_pi_random_frames(seed: int, axis: np.ndarray, angle: float) -> None:
    R1 = random_rotation(np.random.default_rng(seed))
    R2 = R1 @ rot_about(axis, angle)
    err = abs(float(geodesic_angle(R1, R2)) - angle)
    assert err < 1e-7  # the acceptance criterion
    assert err < 1e-12  # what the atan2 form achieves; arccos would be off by up to ~1.5e-8


def test_geodesic_angle_beats_arccos_form() -> None:
    """Documents why the atan2 form is required: arccos is off by > 1e-9 rad at 1e-8 and pi - 1e-8."""
    for angle in (1e-8, np.pi - 1e-8):
        R = rot_about(np.array([0.0, 0.6, 0.8]), angle)
        naive = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
        assert abs(naive - angle) > 1e-9
        assert abs(geodesic_angle(np.eye(3), R) - angle) < 1e-13


def test_geodesic_angle_broadcasts_and_is_symmetric() -> None:
    rng = np.random.default_rng(5)
    R1 = random_rotation(rng, 6).reshape(2, 3, 3, 3)
    R2 = random_rotation(rng)
    a = geodesic_angle(R1, R2)
    assert a.shape == (2, 3)
    assert np.allclose(a, geodesic_angle(R2, R1), atol=1e-15)
    assert np.all((a >= 0) & (a <= np.pi))
    q1, q2 = matrix_to_quaternion(R1), matrix_to_quaternion(R2)
    assert np.allclose(quaternion_angle(q1, q2), a, atol=1e-13)
    assert np.allclose(quaternion_angle(q1, -q2), a, atol=1e-13)  # sign-invariant


# --- nearest rotation -----------------------------------------------------------------------------------------


@settings(max_examples=40, **DETERMINISTIC)
@given(seeds, st.sampled_from([1e-9, 1e-4, 0.1, 1.0, 10.0]), st.booleans())
def test_orthonormalize_is_the_nearest_rotation(seed: int, noise: float, reflect: bool) -> None:
    rng = np.random.default_rng(seed)
    M = random_rotation(rng) @ (np.diag([1.0, 1.0, -1.0]) if reflect else np.eye(3))
    M = M + noise * rng.standard_normal((3, 3))
    R = orthonormalize(M)
    assert is_rotation(R, tol=1e-12) and np.linalg.det(R) > 0
    # independent oracle: Horn's quaternion eigenproblem maximises trace(R^T M) over SO(3)
    Q = nearest_rotation_horn(M)
    assert np.linalg.norm(M - R) <= np.linalg.norm(M - Q) + 1e-12
    # and no nearby rotation is closer
    for _ in range(10):
        P = R @ axis_angle_to_matrix(1e-3 * rng.standard_normal(3))
        assert np.linalg.norm(M - R) <= np.linalg.norm(M - P) + 1e-12


def test_orthonormalize_recovers_rotation_from_small_noise() -> None:
    rng = np.random.default_rng(3)
    R = random_rotation(rng, 50)
    R_back = orthonormalize(R + 1e-7 * rng.standard_normal(R.shape))
    assert np.all(is_rotation(R_back, tol=1e-12))
    assert rotation_error(R_back, R) < 1e-6
    assert rotation_error(orthonormalize(R), R) < 1e-15  # a rotation is its own nearest rotation


def test_orthonormalize_pure_reflections() -> None:
    for M in (np.diag([1.0, 1.0, -1.0]), -np.eye(3), np.diag([-1.0, 1.0, 1.0])):
        R = orthonormalize(M)
        assert is_rotation(R, tol=1e-12)
        # every nearest rotation of a reflection is at Frobenius distance 2 (one axis flipped)
        assert np.linalg.norm(M - R) == pytest.approx(2.0, abs=1e-12)


def test_orthonormalize_rejects_nan() -> None:
    with pytest.raises(InputError, match="NaN"):
        orthonormalize(np.full((3, 3), np.nan))


# --- quaternion signs ------------------------------------------------------------------------------------------


quaternions = st.lists(st.floats(-1, 1, allow_nan=False) | st.sampled_from([0.0, -0.0]), min_size=4, max_size=4)


@settings(max_examples=80, **DETERMINISTIC)
@given(quaternions)
def test_canonical_sign_properties(values: list[float]) -> None:
    q = np.array(values)
    c = quaternion_canonicalize(q)
    assert np.array_equal(np.abs(c), np.abs(q))  # only the sign changes
    assert np.array_equal(c, quaternion_canonicalize(-q))  # q and -q get one representative
    assert np.array_equal(c, quaternion_canonicalize(c))  # idempotent
    assert c[0] >= 0
    nz = np.flatnonzero(c)
    if nz.size:
        assert c[nz[0]] > 0  # the first non-zero component decides, so w = 0 has a deterministic tie-break
    assert not np.any(np.signbit(c[c == 0]))  # no -0.0


@pytest.mark.parametrize(
    ("q", "expected"),
    [
        ([0.0, -0.6, 0.8, 0.0], [0.0, 0.6, -0.8, 0.0]),  # w = 0: x decides
        ([0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 1.0, 0.0]),  # w = x = 0: y decides
        ([0.0, 0.0, 0.0, -1.0], [0.0, 0.0, 0.0, 1.0]),  # only z left
        ([-0.0, -0.0, 0.6, -0.8], [0.0, 0.0, 0.6, -0.8]),  # signed zeros are zeros
        ([-0.5, 0.5, 0.5, 0.5], [0.5, -0.5, -0.5, -0.5]),  # w < 0 flips
    ],
)
def test_canonical_sign_tie_breaks(q: list[float], expected: list[float]) -> None:
    out = quaternion_canonicalize(np.array(q))
    assert np.array_equal(out, expected) and not np.any(np.signbit(out[out == 0]))


@pytest.mark.parametrize("axis", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, -0.6, 0.8], [-1.0, 0, 0]])
def test_half_turn_quaternion_is_deterministic(axis: list[float]) -> None:
    """Exact half turns (w = 0): the matrix -> quaternion result follows the tie-break."""
    k = np.array(axis)
    R = 2 * np.outer(k, k) - np.eye(3)  # rotation by exactly pi about k
    q = matrix_to_quaternion(R)
    assert q[0] == 0.0
    assert np.allclose(q[1:], k * np.sign(k[np.flatnonzero(k)[0]]), atol=1e-15)
    assert np.array_equal(q, matrix_to_quaternion(R.copy()))


@settings(max_examples=40, **DETERMINISTIC)
@given(seeds)
def test_quaternion_product_matches_matrix_product(seed: int) -> None:
    rng = np.random.default_rng(seed)
    q1, q2 = quaternion_normalize(rng.standard_normal((2, 4)))
    R12 = quaternion_to_matrix(q1) @ quaternion_to_matrix(q2)
    assert np.allclose(quaternion_to_matrix(quaternion_multiply(q1, q2)), R12, atol=1e-14)
    assert np.allclose(quaternion_to_matrix(-q1), quaternion_to_matrix(q1), atol=1e-15)


def test_skew_is_the_cross_product() -> None:
    rng = np.random.default_rng(0)
    v, u = rng.standard_normal((2, 5, 3))
    assert np.allclose(skew(v) @ u[..., None], np.cross(v, u)[..., None], atol=1e-15)
    assert np.array_equal(skew(v), -np.swapaxes(skew(v), -1, -2))


# --- 6D Gram-Schmidt ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("sin", [1e-1, 1e-3, 1e-5, 2e-6])
def test_6d_nearly_parallel_halves_give_orthonormal_matrices(sin: float) -> None:
    """Regression: one Gram-Schmidt pass left ``b1 . b2 ~ 1e-16 / sin`` (5e-11 at sin = 1e-5)."""
    rng = np.random.default_rng(1)
    a = rng.standard_normal((500, 3))
    d = np.cross(a, rng.standard_normal((500, 3)))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d6 = np.concatenate([a, a + sin * np.linalg.norm(a, axis=1, keepdims=True) * d], axis=1)
    R = rotation_6d_to_matrix(d6)
    assert np.all(is_rotation(R, tol=1e-14))
    assert np.allclose(R[..., 0], a / np.linalg.norm(a, axis=1, keepdims=True), atol=1e-15)


# --- NaN rows and batching -------------------------------------------------------------------------------------


def _batch_with_bad_rows(good: np.ndarray, bad_value: float) -> np.ndarray:
    out = np.repeat(good[None], 4, axis=0)
    out[1].flat[0] = bad_value
    return out


CONVERTERS = {
    "axis_angle_to_matrix": (axis_angle_to_matrix, np.array([0.1, -0.2, 0.3])),
    "quaternion_to_matrix": (quaternion_to_matrix, np.array([0.9, 0.1, -0.2, 0.3])),
    "quaternion_normalize": (quaternion_normalize, np.array([0.9, 0.1, -0.2, 0.3])),
    "matrix_to_quaternion": (matrix_to_quaternion, rot_about(np.array([0.0, 0.6, 0.8]), 1.0)),
    "matrix_to_axis_angle": (matrix_to_axis_angle, rot_about(np.array([0.0, 0.6, 0.8]), 1.0)),
    "matrix_to_euler": (lambda R: matrix_to_euler(R, "ZYX"), rot_about(np.array([0.0, 0.6, 0.8]), 1.0)),
    "euler_to_matrix": (lambda e: euler_to_matrix(e, "xyz"), np.array([0.1, -0.2, 0.3])),
    "geodesic_angle": (lambda R: geodesic_angle(R, np.eye(3)), rot_about(np.array([0.0, 0.6, 0.8]), 1.0)),
}


@pytest.mark.parametrize("bad_value", [np.nan, np.inf, -np.inf, 1e300])
@pytest.mark.parametrize("name", sorted(CONVERTERS))
def test_converters_propagate_bad_rows_quietly(name: str, bad_value: float) -> None:
    fn, good = CONVERTERS[name]
    batch = _batch_with_bad_rows(good, bad_value)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no RuntimeWarning, whatever pytest's -W says
        out = fn(batch)
    ref = fn(good)
    for i in (0, 2, 3):
        assert np.array_equal(out[i], ref)  # good rows are untouched
    if not np.isfinite(bad_value):
        assert np.all(np.isnan(out[1]))  # the whole row, not just some entries
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert np.all(np.isnan(fn(batch[1])))  # unbatched input too


def test_is_rotation_on_bad_rows() -> None:
    batch = _batch_with_bad_rows(np.eye(3), np.nan)
    batch[2] *= 1e300
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert is_rotation(batch).tolist() == [True, False, False, True]


@settings(max_examples=20, **DETERMINISTIC)
@given(seeds, st.lists(st.integers(1, 3), min_size=0, max_size=3))
def test_batched_leading_dims_match_per_element(seed: int, lead: list[int]) -> None:
    shape = tuple(lead)
    n = int(np.prod(shape, dtype=int))
    R = random_rotation(np.random.default_rng(seed), n).reshape(*shape, 3, 3)
    outs = {
        "q": matrix_to_quaternion(R),
        "rv": matrix_to_axis_angle(R),
        "d6": matrix_to_rotation_6d(R),
        "eul": matrix_to_euler(R, "ZXZ"),
    }
    assert outs["q"].shape == (*shape, 4) and outs["rv"].shape == (*shape, 3)
    assert outs["d6"].shape == (*shape, 6) and outs["eul"].shape == (*shape, 3)
    for idx in np.ndindex(*shape):
        assert np.array_equal(outs["q"][idx], matrix_to_quaternion(R[idx]))
        assert np.array_equal(outs["rv"][idx], matrix_to_axis_angle(R[idx]))
        assert np.array_equal(outs["eul"][idx], matrix_to_euler(R[idx], "ZXZ"))
    for back in (
        quaternion_to_matrix(outs["q"]),
        axis_angle_to_matrix(outs["rv"]),
        rotation_6d_to_matrix(outs["d6"]),
        euler_to_matrix(outs["eul"], "ZXZ"),
    ):
        assert back.shape == R.shape
        assert n == 0 or rotation_error(back, R) < 1e-14

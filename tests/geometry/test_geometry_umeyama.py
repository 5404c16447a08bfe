"""Umeyama / Kabsch: exact recovery, far-from-origin precision, and degenerate inputs."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_testdata import DETERMINISTIC, log_scales, random_sim3_parts, rotation_error, seeds
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry import kabsch, random_rotation, umeyama
from cadalign.types import Rigid3, Sim3

EXACT = 1e-9
"""Acceptance criterion: relative error of a noiseless recovery."""

offsets = st.lists(st.floats(-5e6, 5e6), min_size=3, max_size=3).map(np.array)


def _check_exact(est: Sim3, s: float, R: np.ndarray, t: np.ndarray, src: np.ndarray, dst: np.ndarray) -> None:
    assert abs(est.s / s - 1) < EXACT
    assert rotation_error(est.R, R) < EXACT
    t_scale = np.linalg.norm(t) + s * np.max(np.abs(src)) + 1.0
    assert np.linalg.norm(est.t - t) < EXACT * t_scale
    spread = np.sqrt(np.mean(np.sum((dst - dst.mean(0)) ** 2, axis=1)))
    assert np.max(np.linalg.norm(est.apply(src) - dst, axis=1)) < EXACT * spread


@settings(max_examples=40, **DETERMINISTIC)
@given(seeds, st.integers(3, 60))
def test_recovers_random_sim3_exactly(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    s, R, t = random_sim3_parts(rng)
    src = rng.uniform(-5, 5, (n, 3))
    dst = s * src @ R.T + t
    _check_exact(umeyama(src, dst), s, R, t, src, dst)


@settings(max_examples=60, **DETERMINISTIC)
@given(seeds, offsets, offsets, log_scales)
def test_exact_far_from_origin(seed: int, src_offset: np.ndarray, dst_offset: np.ndarray, s: float) -> None:
    """UTM-like coordinates: points centred up to 5e6 m from the origin, scales 1e-3..1e3.

    Both clouds span >= 10 m: float64 stores a coordinate near 5e6 m only to
    ulp/2 = 4.7e-10 m, so a cloud much smaller than ~1 m would not *contain*
    1e-9 of rotation information, whatever the algorithm. The residual check
    below holds for any spread.
    """
    rng = np.random.default_rng(seed)
    R = random_rotation(rng)
    spread = 10.0 * max(1.0, 1.0 / s)
    local = spread * rng.uniform(-1, 1, (40, 3))
    src = src_offset + local
    t = dst_offset - s * (R @ src_offset)  # puts the dst centre at dst_offset
    dst = s * src @ R.T + t
    est = umeyama(src, dst)
    _check_exact(est, s, R, t, src, dst)
    # scale-free: the fitted map reproduces dst to a few ulps of the coordinates
    ulp = np.spacing(np.max(np.abs(dst)) + np.max(np.abs(s * src)))
    assert np.max(np.abs(est.apply(src) - dst)) < 8 * ulp + 1e-9 * s * spread


@pytest.mark.parametrize("offset", [1e6, 5e6, 1e7])
def test_naive_centring_would_fail_here(offset: float) -> None:
    """The far-field case above is a real test: uncentred covariances lose ~offset^2 * eps / spread^2."""
    rng = np.random.default_rng(0)
    R = random_rotation(rng)
    src = offset + rng.uniform(-10, 10, (40, 3))
    dst = src @ R.T
    est = kabsch(src, dst)
    assert rotation_error(est.R, R) < EXACT
    naive_cov = dst.T @ src / 40 - np.outer(dst.mean(0), src.mean(0))  # one-pass formula
    U, _, Vt = np.linalg.svd(naive_cov)
    R_naive = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    assert rotation_error(R_naive, R) > 100 * EXACT


@settings(max_examples=20, **DETERMINISTIC)
@given(seeds)
def test_without_scale_and_kabsch(seed: int) -> None:
    rng = np.random.default_rng(seed)
    _, R, t = random_sim3_parts(rng)
    src = rng.uniform(-5, 5, (10, 3))
    dst = src @ R.T + t
    est = umeyama(2.0 * src, dst, with_scale=False)  # the true map has scale 1/2; s must stay 1
    assert est.s == 1.0
    rig = kabsch(src, dst)
    assert isinstance(rig, Rigid3)
    assert rotation_error(rig.R, R) < EXACT and np.allclose(rig.t, t, atol=1e-9)


def test_planar_points_and_reflected_targets() -> None:
    rng = np.random.default_rng(1)
    s, R, t = random_sim3_parts(rng)
    src = np.c_[rng.uniform(-1, 1, (12, 2)), np.zeros(12)]  # rank 2: the det fix must still give R
    dst = s * src @ R.T + t
    _check_exact(umeyama(src, dst), s, R, t, src, dst)
    # a mirrored target has no rotation solution: the result is still a proper rotation
    est = umeyama(src[:, [0, 2, 1]] + rng.uniform(0, 1, (12, 3)), src)
    assert np.linalg.det(est.R) == pytest.approx(1.0, abs=1e-12)


def test_weights_ignore_outliers() -> None:
    rng = np.random.default_rng(2)
    s, R, t = random_sim3_parts(rng)
    src = rng.uniform(-5, 5, (20, 3))
    dst = s * src @ R.T + t
    dst[:5] += 100.0  # outliers
    w = np.r_[np.zeros(5), rng.uniform(0.5, 2, 15)]
    _check_exact(umeyama(src, dst, weights=w), s, R, t, src[5:], dst[5:])
    with pytest.raises(InputError, match="weights"):
        umeyama(src, dst, weights=-w)
    with pytest.raises(InputError, match="weights"):
        umeyama(src, dst, weights=w[:5])
    with pytest.raises(DegenerateGeometryError, match="positive weight"):
        umeyama(src, dst, weights=np.r_[np.ones(2), np.zeros(18)])


_rng = np.random.default_rng(3)
_GOOD = _rng.uniform(-1, 1, (6, 3))
_LINE = np.outer(np.linspace(-1, 1, 6), [0.3, -0.5, 0.8])


@pytest.mark.parametrize(
    ("src", "dst", "match"),
    [
        (_GOOD[:2], _GOOD[:2], "at least 3"),
        (np.zeros((0, 3)), np.zeros((0, 3)), "at least 3"),
        (np.ones((6, 3)), _GOOD, "src points are coincident"),
        (_GOOD, np.full((6, 3), 5e6), "dst points are coincident"),
        (_LINE, _GOOD, "src points are collinear"),
        (_GOOD, _LINE + 5e6, "dst points are collinear"),
        (np.where(np.eye(6, 3, dtype=bool), np.nan, _GOOD), _GOOD, "src contains .* non-finite"),
        (_GOOD, np.where(np.eye(6, 3, dtype=bool), np.inf, _GOOD), "dst contains .* non-finite"),
        (_GOOD, _GOOD[:5], "correspond one to one"),
    ],
)
def test_degenerate_inputs_raise(src: np.ndarray, dst: np.ndarray, match: str) -> None:
    with pytest.raises(DegenerateGeometryError, match=match):
        umeyama(src, dst)
    with pytest.raises(DegenerateGeometryError, match=match):
        kabsch(src, dst)


def test_mismatched_shapes_is_also_an_input_error() -> None:
    with pytest.raises(InputError, match="correspond one to one"):
        umeyama(_GOOD, _GOOD[:4])


def test_wrong_dimension_raises_input_error() -> None:
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        umeyama(_GOOD[:, :2], _GOOD[:, :2])


def test_near_coincident_at_large_offset_is_rejected_not_garbage() -> None:
    src = 5e6 + 1e-5 * _rng.standard_normal((10, 3))  # 1e-5 m spread is 2e-12 relative: noise at float64
    with pytest.raises(DegenerateGeometryError, match="coincident"):
        umeyama(src, _GOOD[:1].repeat(10, 0) + _rng.standard_normal((10, 3)))

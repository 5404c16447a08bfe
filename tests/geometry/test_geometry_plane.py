"""Plane fits: unit normal and its sign convention, accuracy under noise, far-from-origin data, degeneracies."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_testdata import DETERMINISTIC, seeds, unit_vectors
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry import Plane, fit_plane, lift_from_plane_2d, plane_basis, project_to_plane_2d

MAX_NORMAL_ERR_DEG = 0.1
"""Acceptance criterion: normal error on noisy points."""

offsets = st.lists(st.floats(-5e6, 5e6), min_size=3, max_size=3).map(np.array)


def _plane_points(rng: np.random.Generator, n: np.ndarray, centre: np.ndarray, count: int, half: float) -> np.ndarray:
    u, v = plane_basis(n)
    xy = rng.uniform(-half, half, (count, 2))
    return centre + xy[:, :1] * u + xy[:, 1:] * v


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b)), a @ b)))


@settings(max_examples=40, **DETERMINISTIC)
@given(seeds, unit_vectors, offsets, st.sampled_from([0.0, 1e-3, 1e-2]))
def test_fit_plane_normal_accuracy_and_sign(seed: int, n: np.ndarray, offset: np.ndarray, sigma: float) -> None:
    """Noisy points (sigma up to 1 cm over a 10 m patch) at up to 5e6 m: error <= 0.1 deg, normal faces origin."""
    rng = np.random.default_rng(seed)
    P = _plane_points(rng, n, offset, 200, 5.0) + sigma * rng.standard_normal((200, 3))
    plane = fit_plane(P)
    assert abs(np.linalg.norm(plane.normal) - 1) < 1e-15
    n_true = n if n @ (0 - offset) > 0 else -n
    if abs(n @ offset) > 1.0:  # the origin is clearly off the plane: the sign is defined by it
        assert _angle_deg(plane.normal, n_true) <= MAX_NORMAL_ERR_DEG
    else:
        assert min(_angle_deg(plane.normal, n), _angle_deg(plane.normal, -n)) <= MAX_NORMAL_ERR_DEG
    assert plane.normal @ (0 - plane.centroid) >= 0 or abs(n @ offset) <= 1.0
    assert abs(plane.offset + plane.normal @ plane.centroid) <= 1e-9 * (1 + np.abs(offset).max())
    ulp = np.spacing(np.abs(offset).max() + 10.0)  # the rounding of the input coordinates
    assert plane.rms == pytest.approx(np.sqrt(np.mean(plane.signed_distance(P) ** 2)), rel=1e-6, abs=4 * ulp)
    if sigma == 0:
        assert _angle_deg(plane.normal, n_true) < 1e-7 or abs(n @ offset) <= 1.0
        assert plane.rms < 1e-8


@settings(max_examples=30, **DETERMINISTIC)
@given(seeds, unit_vectors, offsets)
def test_fit_plane_exact_far_from_origin(seed: int, n: np.ndarray, offset: np.ndarray) -> None:
    rng = np.random.default_rng(seed)
    P = _plane_points(rng, n, offset, 50, 10.0)
    plane = fit_plane(P, toward=offset + 3.0 * n)
    assert _angle_deg(plane.normal, n) < 1e-8  # toward = a point on the +n side
    assert np.max(np.abs(plane.signed_distance(P))) < 4 * np.spacing(np.abs(offset).max() + 10.0)


def test_sign_convention_toward_and_tie_break() -> None:
    rng = np.random.default_rng(0)
    floor = np.c_[rng.uniform(-1, 1, (20, 2)), np.full(20, -2.0)]  # z = -2 plane seen from the origin
    assert np.allclose(fit_plane(floor).normal, [0, 0, 1], atol=1e-15)
    assert np.allclose(fit_plane(floor, toward=np.array([0, 0, -5.0])).normal, [0, 0, -1], atol=1e-15)
    # toward lies in the plane: the documented tie-break is z up, then y, then x
    through_origin = np.c_[rng.uniform(-1, 1, (20, 2)), np.zeros(20)]
    assert np.allclose(fit_plane(through_origin).normal, [0, 0, 1], atol=1e-15)
    wall_xz = np.c_[rng.uniform(-1, 1, 20), np.zeros(20), rng.uniform(-1, 1, 20)]
    assert np.allclose(fit_plane(wall_xz).normal, [0, 1, 0], atol=1e-15)
    wall_yz = np.c_[np.zeros(20), rng.uniform(-1, 1, (20, 2))]
    assert np.allclose(fit_plane(wall_yz).normal, [1, 0, 0], atol=1e-15)


@pytest.mark.parametrize(
    ("points", "match"),
    [
        (np.zeros((2, 3)), "at least 3"),
        (np.ones((6, 3)), "coincident"),
        (5e6 + 1e-6 * np.random.default_rng(1).standard_normal((6, 3)), "coincident"),
        (np.outer(np.linspace(0, 1, 6), [1.0, 2.0, 3.0]), "collinear"),
        (5e6 + np.outer(np.linspace(0, 1, 6), [1.0, 2.0, 3.0]), "collinear"),
        (np.array([[0.0, 0, 0], [1, 0, 0], [2, 1e-9, 0], [3, 0, 0]]), "collinear"),
        (np.array([[0.0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), "non-finite"),
    ],
)
def test_fit_plane_rejects_degenerate(points: np.ndarray, match: str) -> None:
    with pytest.raises(DegenerateGeometryError, match=match):
        fit_plane(points)


def test_fit_plane_input_errors() -> None:
    with pytest.raises(InputError):
        fit_plane(np.zeros((5, 2)))
    with pytest.raises(InputError):
        fit_plane(np.eye(3), toward=np.array([np.nan, 0, 0]))
    with pytest.raises(InputError):
        Plane(normal=np.zeros(2), offset=0.0, centroid=np.zeros(3), rms=0.0)


@settings(max_examples=40, **DETERMINISTIC)
@given(unit_vectors | st.sampled_from([np.array([0.0, 0, -1]), np.array([0.0, 0, 1]), np.array([1.0, 0, 0])]))
def test_plane_basis_is_right_handed_orthonormal(n: np.ndarray) -> None:
    u, v = plane_basis(n)
    B = np.stack([u, v, n], axis=1)
    assert np.allclose(B.T @ B, np.eye(3), atol=1e-15)
    assert np.allclose(np.cross(u, v), n, atol=1e-15)


def test_plane_basis_batched_and_errors() -> None:
    n = np.random.default_rng(2).standard_normal((4, 5, 3))
    u, v = plane_basis(n)
    assert u.shape == v.shape == (4, 5, 3)
    with pytest.raises(DegenerateGeometryError):
        plane_basis(np.zeros(3))
    with pytest.raises(InputError):
        plane_basis(np.array([np.nan, 0, 1]))


def test_project_lift_round_trip() -> None:
    rng = np.random.default_rng(3)
    n = np.array([0.2, -0.3, 0.9])
    P = _plane_points(rng, n / np.linalg.norm(n), np.array([4e6, -1e6, 30.0]), 30, 8.0)
    plane = fit_plane(P)
    xy = project_to_plane_2d(P, plane)
    assert xy.shape == (30, 2)
    assert np.allclose(lift_from_plane_2d(xy, plane), P, atol=1e-8)
    # CCW in (x, y) is CCW seen from the normal's side
    tri = lift_from_plane_2d(np.array([[0.0, 0], [1, 0], [0, 1]]), plane)
    assert np.cross(tri[1] - tri[0], tri[2] - tri[0]) @ plane.normal > 0

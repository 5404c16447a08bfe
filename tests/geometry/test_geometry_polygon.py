"""2D convex hull, polygon area and triangulation: areas add up, orientation is CCW, degeneracies raise."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_testdata import DETERMINISTIC, seeds
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry import convex_hull_2d, fan_triangulate, polygon_area, triangulate_convex_polygon


def _signed_areas(pts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))


@settings(max_examples=40, **DETERMINISTIC)
@given(seeds, st.integers(3, 200), st.sampled_from([0.0, 1e3, 5e6]))
def test_hull_and_triangulation(seed: int, n: int, offset: float) -> None:
    rng = np.random.default_rng(seed)
    pts = offset + rng.uniform(-10, 10, (n, 2))
    pts = np.r_[pts, pts[: n // 4]]  # duplicates must not matter
    hull = convex_hull_2d(pts)
    ref = ConvexHull(pts - offset)
    assert set(hull.tolist()) <= set(range(len(pts)))
    assert sorted({tuple(p) for p in pts[hull]}) == sorted({tuple(p) for p in pts[ref.vertices]})
    area = polygon_area(pts[hull])
    assert area > 0  # CCW
    assert area == pytest.approx(ref.volume, rel=1e-9)
    tris = triangulate_convex_polygon(pts)
    assert tris.shape == (hull.size - 2, 3) and tris.dtype == np.int64
    tri_areas = _signed_areas(pts - offset, tris)
    assert np.all(tri_areas > 0)  # consistent (CCW) orientation
    assert tri_areas.sum() == pytest.approx(area, rel=1e-12)


def test_clockwise_polygon_gives_ccw_triangles() -> None:
    square_cw = np.array([[0.0, 0], [0, 1], [1, 1], [1, 0]])
    assert polygon_area(square_cw) == -1.0
    tris = triangulate_convex_polygon(square_cw)
    assert np.all(_signed_areas(square_cw, tris) > 0)
    assert _signed_areas(square_cw, tris).sum() == pytest.approx(1.0, abs=1e-15)


def test_points_on_edges_and_interior_are_not_hull_vertices() -> None:
    pts = np.array([[0.0, 0], [1, 0], [2, 0], [2, 1], [2, 2], [1, 1], [0, 2], [0, 1], [1, 2]])
    hull = convex_hull_2d(pts)
    assert sorted(map(tuple, pts[hull])) == [(0.0, 0.0), (0.0, 2.0), (2.0, 0.0), (2.0, 2.0)]
    assert tuple(pts[hull[0]]) == (0.0, 0.0)  # starts at the lexicographic minimum


def test_polygon_area_far_from_origin_and_small_inputs() -> None:
    square = np.array([[0.0, 0], [1, 0], [1, 1], [0, 1]])
    assert polygon_area(square + 1e7) == 1.0
    assert polygon_area(square[:2]) == 0.0


@pytest.mark.parametrize(
    ("points", "match"),
    [
        (np.outer(np.arange(6.0), [1.0, 2.0]), "collinear"),
        (np.outer(np.arange(6.0), [1.0, 2.0]) + 5e6, "collinear"),
        (np.array([[0.0, 0], [1, 1e-13], [2, 0]]), "collinear"),
        (np.ones((5, 2)), "coincident"),
        (np.zeros((2, 2)), "at least 3"),
        (np.array([[0.0, 0], [1, 0], [np.nan, 1]]), "non-finite"),
    ],
)
def test_degenerate_hulls_raise(points: np.ndarray, match: str) -> None:
    with pytest.raises(DegenerateGeometryError, match=match):
        convex_hull_2d(points)
    with pytest.raises(DegenerateGeometryError, match=match):
        triangulate_convex_polygon(points)


def test_input_errors() -> None:
    with pytest.raises(InputError):
        convex_hull_2d(np.zeros((5, 3)))
    with pytest.raises(InputError):
        fan_triangulate(2)
    assert fan_triangulate(3).tolist() == [[0, 1, 2]]

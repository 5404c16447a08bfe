"""2D convex hulls, polygon areas and fan triangulation.

Orientation convention: counter-clockwise (CCW) in a right-handed ``(x, y)``
frame has positive signed area. Faces are returned CCW as well.
"""

from __future__ import annotations

import numpy as np

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry._checks import as_points, require_finite

HULL_AREA_REL_TOL = 1e-12
"""Hulls with area below this times (bounding-box diagonal)^2 are collinear."""


def polygon_area(points: np.ndarray) -> float:
    """Signed area (shoelace) of a simple polygon, positive when CCW.

    Vertices are shifted by their mean first so far-from-origin polygons do not
    lose precision to cancellation.

    Args:
        points: (N, 2) vertices in order (not repeating the first at the end).

    Returns:
        The signed area in squared input units; 0 for fewer than 3 vertices.
    """
    p = as_points(points, 2, "points")
    if p.shape[0] < 3:
        return 0.0
    p = p - p.mean(axis=0)
    x, y = p[:, 0], p[:, 1]
    return float(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """z of ``(a - o) x (b - o)``: > 0 for a left (CCW) turn."""
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _half_hull(pts: np.ndarray, order: np.ndarray) -> list[int]:
    """One monotone chain of Andrew's algorithm; pops non-left turns (drops collinear/duplicate points)."""
    chain: list[int] = []
    for idx in order:
        while len(chain) >= 2 and _cross(pts[chain[-2]], pts[chain[-1]], pts[idx]) <= 0:
            chain.pop()
        chain.append(int(idx))
    return chain


def convex_hull_2d(points: np.ndarray) -> np.ndarray:
    """Indices of the convex hull vertices, counter-clockwise (Andrew's monotone chain).

    Starts at the lexicographically smallest ``(x, y)`` vertex. Duplicates and
    points on hull edges are excluded, so every returned vertex is a strict
    corner. O(N log N).

    Args:
        points: (N, 2) points.

    Returns:
        (H,) int64 indices into ``points``, H >= 3.

    Raises:
        InputError: for shapes other than (N, 2).
        DegenerateGeometryError: for N < 3, NaN/inf, or points that are all
            coincident or collinear (hull area below :data:`HULL_AREA_REL_TOL`
            times the squared bounding-box diagonal); there is no 2D hull.
    """
    pts = as_points(points, 2, "points")
    if pts.shape[0] < 3:
        raise DegenerateGeometryError(f"a 2D convex hull needs at least 3 points, got {pts.shape[0]}")
    require_finite(pts, "points")
    order = np.lexsort((pts[:, 1], pts[:, 0]))
    lower = _half_hull(pts, order)
    upper = _half_hull(pts, order[::-1])
    hull = np.asarray(lower[:-1] + upper[:-1], dtype=np.int64)
    diag2 = float(np.sum((pts.max(axis=0) - pts.min(axis=0)) ** 2))
    if hull.size < 3 or polygon_area(pts[hull]) <= HULL_AREA_REL_TOL * diag2:
        raise DegenerateGeometryError("points are coincident or collinear; they have no 2D convex hull")
    return hull


def fan_triangulate(n_vertices: int) -> np.ndarray:
    """Triangle fan ``(0, i, i + 1)`` of a convex polygon with ``n_vertices`` vertices.

    Returns:
        (n - 2, 3) int64 vertex indices; CCW if the polygon is CCW.

    Raises:
        InputError: for fewer than 3 vertices.
    """
    n = int(n_vertices)
    if n < 3:
        raise InputError(f"a polygon needs at least 3 vertices, got {n}")
    i = np.arange(1, n - 1, dtype=np.int64)
    return np.stack([np.zeros_like(i), i, i + 1], axis=1)


def triangulate_convex_polygon(points_2d: np.ndarray) -> np.ndarray:
    """CCW triangles covering the convex hull of ``points_2d`` (any order, any duplicates).

    Args:
        points_2d: (N, 2) points, typically the vertices of a convex polygon.

    Returns:
        (H - 2, 3) int64 indices into ``points_2d``; interior and duplicate
        points are not used.

    Raises:
        DegenerateGeometryError: as :func:`convex_hull_2d`.
    """
    hull = convex_hull_2d(points_2d)
    return hull[fan_triangulate(hull.size)]

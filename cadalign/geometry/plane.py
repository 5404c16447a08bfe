"""Least-squares plane fitting and in-plane 2D coordinates.

A plane is ``n . x + d = 0`` with unit normal ``n`` and offset ``d`` (metres).
The fit works on points centred in float64 (two passes), so point sets a
million metres from the origin keep full precision.

Sign convention: the normal points to the side of the plane holding the
``toward`` point (default: the origin, i.e. the viewer when points are in a
camera frame), ``n . (toward - centroid) > 0``. When ``toward`` lies in the
plane (within rounding) the sign is ambiguous and the tie-break is "z up":
``n_z > 0``, then ``n_y > 0``, then ``n_x > 0`` for the first component that
is not ~0 (> 1e-12).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry._checks import as_batched, as_points, centre, require_finite

COINCIDENT_REL_TOL = 1e-10
"""Points whose RMS spread is below this times their largest coordinate are coincident."""

COLLINEAR_REL_TOL = 1e-6
"""Points whose second singular value (centred) is below this times the first are collinear."""

_SIDE_REL_TOL = 1e-12
_TIE_TOL = 1e-12


@dataclass(frozen=True)
class Plane:
    """A fitted plane ``normal . x + offset = 0``.

    Attributes:
        normal: (3,) unit normal, oriented as described in the module docstring.
        offset: ``d`` in metres, ``-normal . centroid``.
        centroid: (3,) centroid of the fitted points, metres (a point on the plane).
        rms: RMS orthogonal distance of the fitted points to the plane, metres.
    """

    normal: np.ndarray
    offset: float
    centroid: np.ndarray
    rms: float

    def __post_init__(self) -> None:
        for name in ("normal", "centroid"):
            arr = np.array(getattr(self, name), dtype=np.float64)
            if arr.shape != (3,):
                raise InputError(f"Plane.{name} must have shape (3,), got {arr.shape}")
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "offset", float(self.offset))
        object.__setattr__(self, "rms", float(self.rms))

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distances (metres, positive on the normal's side) of points ``(N, 3)`` -> ``(N,)``."""
        pts = as_points(points, 3, "points")
        return (pts - self.centroid) @ self.normal


def _orient(normal: np.ndarray, centroid: np.ndarray, toward: np.ndarray) -> np.ndarray:
    """Flip ``normal`` towards ``toward``; z-up tie-break when ``toward`` is in the plane."""
    side = float(normal @ (toward - centroid))
    if abs(side) > _SIDE_REL_TOL * (np.linalg.norm(toward) + np.linalg.norm(centroid)):
        return normal if side > 0 else -normal
    for comp in (2, 1, 0):
        if abs(normal[comp]) > _TIE_TOL:
            return normal if normal[comp] > 0 else -normal
    return normal  # unreachable for a unit normal


def fit_plane(points: np.ndarray, toward: np.ndarray | None = None) -> Plane:
    """Total-least-squares plane through points (SVD of the centred points).

    Args:
        points: (N, 3) points, metres.
        toward: optional (3,) point the normal should face; default the origin.

    Returns:
        The :class:`Plane` (normal oriented per the module docstring).

    Raises:
        InputError: for shapes other than (N, 3) / (3,) or a non-finite ``toward``.
        DegenerateGeometryError: for N < 3, NaN/inf points, coincident points
            (RMS spread below :data:`COINCIDENT_REL_TOL` times the largest
            coordinate) or collinear points (second singular value below
            :data:`COLLINEAR_REL_TOL` times the first): the plane is undefined.
    """
    P = as_points(points, 3, "points")
    if P.shape[0] < 3:
        raise DegenerateGeometryError(f"a plane fit needs at least 3 points, got {P.shape[0]}")
    require_finite(P, "points")
    target = np.zeros(3) if toward is None else np.asarray(toward, dtype=np.float64)
    if target.shape != (3,) or not np.all(np.isfinite(target)):
        raise InputError(f"toward must be a finite (3,) point, got {toward!r}")
    centred, c = centre(P)
    _, sv, Vt = np.linalg.svd(centred, full_matrices=False)
    sv = sv / np.sqrt(P.shape[0])  # RMS spread along the principal axes
    magnitude = float(np.max(np.abs(P)))
    if sv[0] == 0 or sv[0] <= COINCIDENT_REL_TOL * magnitude:
        raise DegenerateGeometryError(f"points are coincident (RMS spread {sv[0]:.3g}); the plane is undefined")
    if sv[1] <= COLLINEAR_REL_TOL * sv[0]:
        raise DegenerateGeometryError(
            f"points are collinear (singular values {sv[0]:.3g}, {sv[1]:.3g}); the plane is undefined"
        )
    n = _orient(Vt[2] / np.linalg.norm(Vt[2]), c, target)
    return Plane(normal=n, offset=-float(n @ c), centroid=c, rms=float(sv[2]))


def plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal tangent vectors ``(u, v)`` with ``u x v = n`` for any normal.

    Duff et al., "Building an Orthonormal Basis, Revisited" (JCGT 2017):
    branch-free apart from the sign of ``n_z``, with no singularity anywhere on
    the sphere (unlike crossing with a fixed axis).

    Args:
        normal: (..., 3) normals (normalised here).

    Returns:
        ``(u, v)``, each (..., 3).

    Raises:
        InputError: for NaN/inf normals.
        DegenerateGeometryError: for a zero normal.
    """
    n = as_batched(normal, (3,), "normal")
    if not np.all(np.isfinite(n)):
        raise InputError("normal contains NaN or inf")
    norm = np.linalg.norm(n, axis=-1, keepdims=True)
    if np.any(norm == 0):
        raise DegenerateGeometryError("a zero normal has no tangent basis")
    x, y, z = np.moveaxis(n / norm, -1, 0)
    sign = np.copysign(1.0, z)
    a = -1.0 / (sign + z)
    b = x * y * a
    u = np.stack([1.0 + sign * x * x * a, sign * b, -sign * x], axis=-1)
    v = np.stack([b, sign + y * y * a, -y], axis=-1)
    return u, v


def project_to_plane_2d(points: np.ndarray, plane: Plane) -> np.ndarray:
    """In-plane coordinates ``(N, 2)`` (metres) of points ``(N, 3)``, origin at the centroid.

    The axes are :func:`plane_basis` of the normal, so ``(x, y)`` is
    counter-clockwise seen from the side the normal points to.
    """
    pts = as_points(points, 3, "points")
    u, v = plane_basis(plane.normal)
    d = pts - plane.centroid
    return np.stack([d @ u, d @ v], axis=-1)


def lift_from_plane_2d(xy: np.ndarray, plane: Plane) -> np.ndarray:
    """Inverse of :func:`project_to_plane_2d`: 3D points ``(N, 3)`` on the plane from ``(N, 2)``."""
    xy = as_points(xy, 2, "xy")
    u, v = plane_basis(plane.normal)
    return plane.centroid + xy[:, :1] * u + xy[:, 1:] * v

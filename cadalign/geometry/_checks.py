"""Shape and value checks shared by the geometry modules (private)."""

from __future__ import annotations

import numpy as np

from cadalign.errors import DegenerateGeometryError, InputError


def as_batched(x: object, tail: tuple[int, ...], name: str) -> np.ndarray:
    """Return ``x`` as a float64 array of shape ``(..., *tail)``.

    Raises:
        InputError: if the trailing dimensions are not ``tail``.
    """
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim < len(tail) or arr.shape[arr.ndim - len(tail) :] != tail:
        dims = ", ".join(str(d) for d in tail)
        raise InputError(f"{name} must have shape (..., {dims}), got {arr.shape}")
    return arr


def as_points(x: object, dim: int, name: str) -> np.ndarray:
    """Return ``x`` as a float64 array of shape ``(N, dim)``.

    Raises:
        InputError: if ``x`` is not two-dimensional with ``dim`` columns.
    """
    arr = np.asarray(x, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise InputError(f"{name} must have shape (N, {dim}), got {arr.shape}")
    return arr


def require_finite(arr: np.ndarray, name: str) -> None:
    """Raise :class:`DegenerateGeometryError` naming ``name`` if ``arr`` has NaN/inf."""
    if not np.all(np.isfinite(arr)):
        bad = int(np.count_nonzero(~np.isfinite(arr)))
        raise DegenerateGeometryError(
            f"{name} contains {bad} non-finite value(s); the estimate is undefined. "
            "Drop or mask the NaN/inf entries first."
        )


def centre(points: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Subtract the (weighted) centroid in two passes.

    The first pass removes a reference point so the centroid is computed from
    small numbers; the second removes the residual centroid. This keeps points
    lying 1e6-1e7 m from the origin accurate to the float64 grid spacing.

    Args:
        points: (N, D) coordinates.
        weights: optional (N,) non-negative weights with a positive sum.

    Returns:
        ``(centred (N, D), centroid (D,))``.
    """
    ref = points[0]
    shifted = points - ref
    c1 = np.average(shifted, axis=0, weights=weights)
    centred = shifted - c1
    c2 = np.average(centred, axis=0, weights=weights)
    return centred - c2, ref + (c1 + c2)

"""Shape and value checks shared by the geometry modules (private)."""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

import numpy as np

from cadalign.errors import DegenerateGeometryError, InputError

_P = ParamSpec("_P")
_T = TypeVar("_T")


def quiet_nonfinite(fn: Callable[_P, _T]) -> Callable[_P, _T]:
    """Run ``fn`` with numpy's invalid/overflow/divide warnings off.

    For converters that propagate NaN/inf rows into NaN output rows by design:
    a bad row must not emit a RuntimeWarning (which ``-W error`` turns into a
    crash) nor disturb the other rows of the batch. A fresh ``np.errstate`` per
    call keeps nested decorated calls safe.
    """

    @functools.wraps(fn)
    def wrapper(*args: _P.args, **kwargs: _P.kwargs) -> _T:
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            return fn(*args, **kwargs)

    return wrapper


def nan_rows_where_nonfinite(out: np.ndarray, *inputs: tuple[np.ndarray, int]) -> np.ndarray:
    """Set whole output rows to NaN where an input row holds NaN/inf.

    Without this a bad row can come out partly finite (e.g. a NaN Euler angle
    still leaves ``R[0, 0] = 1``), which looks like data.

    Args:
        out: (..., *out_tail) result (an array, or a numpy scalar when
            ``...`` is empty); arrays are modified in place.
        inputs: ``(array (..., *in_tail), len(in_tail))`` pairs whose leading
            dimensions broadcast to those of ``out``.

    Returns:
        ``out`` with the bad rows set to NaN.
    """
    bad = np.zeros((), dtype=bool)
    for arr, n_tail in inputs:
        bad = bad | ~np.all(np.isfinite(arr), axis=tuple(range(-n_tail, 0)))
    if not np.any(bad):
        return out
    if np.ndim(out) == 0:
        return np.float64(np.nan)
    out[bad] = np.nan
    return out


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

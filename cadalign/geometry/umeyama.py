"""Closed-form least-squares similarity / rigid alignment of corresponding 3D points.

Umeyama, "Least-squares estimation of transformation parameters between two
point patterns", TPAMI 1991. Everything is computed in float64 in frames
centred on the (weighted) centroids, so point sets lying millions of metres
from the origin (UTM coordinates) keep their full precision.
"""

from __future__ import annotations

import numpy as np

from cadalign.errors import CorrespondenceError, DegenerateGeometryError, InputError
from cadalign.geometry._checks import as_points, centre, require_finite
from cadalign.types import Rigid3, Sim3

COINCIDENT_REL_TOL = 1e-10
"""Points whose RMS spread is below this times their largest coordinate are coincident."""

COLLINEAR_REL_TOL = 1e-6
"""Points whose second singular value (centred) is below this times the first are collinear."""


def _check_inputs(src: object, dst: object, weights: object | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated ``(src (N, 3), dst (N, 3), weights (N,))`` in float64."""
    src_a = as_points(src, 3, "src")
    dst_a = as_points(dst, 3, "dst")
    if src_a.shape != dst_a.shape:
        raise CorrespondenceError(
            f"src and dst must correspond one to one, got shapes {src_a.shape} and {dst_a.shape}; "
            "pass the same number of matched points in both"
        )
    n = src_a.shape[0]
    if n < 3:
        raise DegenerateGeometryError(f"alignment needs at least 3 point pairs, got {n}")
    require_finite(src_a, "src")
    require_finite(dst_a, "dst")
    if weights is None:
        return src_a, dst_a, np.ones(n)
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n,):
        raise InputError(f"weights must have shape ({n},), got {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise InputError("weights must be finite and non-negative")
    if np.count_nonzero(w > 0) < 3:
        raise DegenerateGeometryError("alignment needs at least 3 point pairs with positive weight")
    return src_a, dst_a, w


def _check_spread(centred: np.ndarray, w: np.ndarray, magnitude: float, name: str) -> float:
    """Raise if centred points are coincident or collinear; return the weighted variance.

    Args:
        centred: (N, 3) points minus their weighted centroid.
        w: (N,) weights.
        magnitude: largest absolute input coordinate, for the relative test.
        name: the input's name for the message.
    """
    sw = np.sqrt(w / w.sum())[:, None]
    sv = np.linalg.svd(centred * sw, compute_uv=False)  # RMS spread along the principal axes
    if sv[0] <= COINCIDENT_REL_TOL * magnitude or sv[0] == 0:
        raise DegenerateGeometryError(
            f"{name} points are coincident (RMS spread {sv[0]:.3g} at coordinates up to {magnitude:.3g}); "
            "scale and rotation are undefined"
        )
    if sv[1] <= COLLINEAR_REL_TOL * sv[0]:
        raise DegenerateGeometryError(
            f"{name} points are collinear (singular values {sv[0]:.3g}, {sv[1]:.3g}); "
            "the rotation about their line is undefined"
        )
    return float(np.sum(sv**2))


def umeyama(
    src: np.ndarray,
    dst: np.ndarray,
    with_scale: bool = True,
    weights: np.ndarray | None = None,
) -> Sim3:
    """Least-squares similarity ``dst ~ s R src + t`` (``T_dst_from_src``).

    Minimises ``sum_i w_i |dst_i - (s R src_i + t)|^2`` in closed form (SVD of
    the weighted cross-covariance, with the determinant fix so the result is a
    rotation, never a reflection).

    Args:
        src: (N, 3) points in the source frame.
        dst: (N, 3) corresponding points in the destination frame.
        with_scale: estimate ``s``; if False ``s = 1`` (Kabsch).
        weights: optional (N,) non-negative per-pair weights.

    Returns:
        The :class:`Sim3` mapping ``src`` to ``dst``.

    Raises:
        InputError: for arrays not shaped (N, 3) or invalid weights.
        CorrespondenceError: (an InputError and a DegenerateGeometryError) for
            ``src`` and ``dst`` with different numbers of points.
        DegenerateGeometryError: for fewer than 3 pairs, NaN/inf, coincident
            points (RMS spread below :data:`COINCIDENT_REL_TOL` times the
            largest coordinate), collinear points (second singular value below
            :data:`COLLINEAR_REL_TOL` times the first) in ``src`` or ``dst``, or
            a rank-deficient cross-covariance (inconsistent correspondences).

    >>> src = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    >>> T = umeyama(src, 2.0 * src + [1.0, 2.0, 3.0])
    >>> round(T.s, 9), T.t.round(9).tolist(), bool(np.allclose(T.R, np.eye(3)))
    (2.0, [1.0, 2.0, 3.0], True)
    """
    src_a, dst_a, w = _check_inputs(src, dst, weights)
    x, mu_src = centre(src_a, w)
    y, mu_dst = centre(dst_a, w)
    var_src = _check_spread(x, w, float(np.max(np.abs(src_a))), "src")
    _check_spread(y, w, float(np.max(np.abs(dst_a))), "dst")
    cov = (y * (w / w.sum())[:, None]).T @ x  # sum_i w_i y_i x_i^T / W, (3, 3)
    U, D, Vt = np.linalg.svd(cov)
    if D[1] <= COLLINEAR_REL_TOL * D[0]:
        raise DegenerateGeometryError(
            f"cross-covariance of src and dst has rank < 2 (singular values {D}); "
            "the correspondences do not determine a rotation"
        )
    d = np.array([1.0, 1.0, -1.0 if np.linalg.det(U) * np.linalg.det(Vt) < 0 else 1.0])
    R = (U * d) @ Vt
    s = float(np.dot(D, d) / var_src) if with_scale else 1.0
    return Sim3(s, R, mu_dst - s * (R @ mu_src))


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> Rigid3:
    """Least-squares rigid transform ``dst ~ R src + t`` (``T_dst_from_src``).

    Same inputs, checks and errors as :func:`umeyama` with ``with_scale=False``.

    Args:
        src: (N, 3) points in the source frame.
        dst: (N, 3) corresponding points in the destination frame.
        weights: optional (N,) non-negative per-pair weights.

    Returns:
        The :class:`Rigid3` mapping ``src`` to ``dst``.
    """
    return umeyama(src, dst, with_scale=False, weights=weights).rigid()

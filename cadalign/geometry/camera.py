"""Pinhole camera helpers: intrinsics, projection, back-projection, pixel rays.

Pixel convention (see :mod:`cadalign.types`): pixel ``(u, v)`` with integer
``u`` covers ``[u, u+1)`` and its centre is at ``u + 0.5``, so the centre of
pixel column ``i``, row ``j`` back-projects along ``K^-1 (i + 0.5, j + 0.5, 1)``.
Camera frame: ``x`` right, ``y`` down, ``z`` forward (OpenCV/COLMAP); depth is
the ``z`` coordinate in metres, not the distance along the ray.

Invalid inputs (depth <= 0, NaN, inf, points behind the camera) never raise
and never emit a RuntimeWarning: they give NaN rows and ``valid = False``.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry._checks import as_points

FOCAL_SHIFT_COND_TOL = 1e-6
"""Focal/shift fits whose column-normalised Jacobian has ``sigma_min / sigma_max`` below this are rejected.

The ratio is about the relative depth variation ``std(Z) / (Z + dz)``; below
1e-6 the point map is numerically a fronto-parallel plane."""

_MIN_SHIFTED_DEPTH = 1e-9
"""Lower bound on ``Z + dz`` in the unit-RMS frame of the focal/shift solve."""


def intrinsics(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """The (3, 3) intrinsic matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (pixels).

    Raises:
        InputError: if any value is non-finite or a focal length is not positive.

    >>> intrinsics(500.0, 500.0, 320.0, 240.0)
    array([[500.,   0., 320.],
           [  0., 500., 240.],
           [  0.,   0.,   1.]])
    """
    vals = np.array([fx, fy, cx, cy], dtype=np.float64)
    if not np.all(np.isfinite(vals)) or fx <= 0 or fy <= 0:
        raise InputError(f"intrinsics must be finite with fx, fy > 0, got fx={fx}, fy={fy}, cx={cx}, cy={cy}")
    return np.array([[vals[0], 0.0, vals[2]], [0.0, vals[1], vals[3]], [0.0, 0.0, 1.0]])


def decompose_intrinsics(K: np.ndarray) -> tuple[float, float, float, float]:
    """The inverse of :func:`intrinsics`: ``(fx, fy, cx, cy)`` in pixels from a (3, 3) ``K``.

    Raises:
        InputError: if ``K`` is not a finite upper-triangular intrinsic matrix
            with positive focal lengths, or has a non-zero skew ``K[0, 1]``
            (not representable by four numbers).
    """
    K = _check_K(K)
    if K[0, 1] != 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"K must have zero skew and positive focal lengths to decompose, got\n{K}")
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def fov_to_focal(fov_rad: float, size_px: float) -> float:
    """Focal length (pixels) giving a full field of view ``fov_rad`` across ``size_px`` pixels.

    Raises:
        InputError: unless ``0 < fov_rad < pi`` and ``size_px > 0``.
    """
    if not (0 < fov_rad < np.pi) or not (size_px > 0):
        raise InputError(f"need 0 < fov_rad < pi and size_px > 0, got {fov_rad}, {size_px}")
    return float(0.5 * size_px / np.tan(0.5 * fov_rad))


def focal_to_fov(focal_px: float, size_px: float) -> float:
    """Full field of view (radians) across ``size_px`` pixels for focal length ``focal_px`` (pixels).

    Raises:
        InputError: unless both are finite and positive.
    """
    if not (0 < focal_px < np.inf) or not (0 < size_px < np.inf):
        raise InputError(f"need finite focal_px > 0 and size_px > 0, got {focal_px}, {size_px}")
    return float(2.0 * np.arctan2(0.5 * size_px, focal_px))


def _check_K(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InputError(f"K must be a finite (3, 3) matrix, got shape {K.shape}")
    if K[1, 0] != 0 or not np.array_equal(K[2], [0.0, 0.0, 1.0]) or K[0, 0] == 0 or K[1, 1] == 0:
        raise InputError(f"K must be upper triangular with K[2] = (0, 0, 1) and non-zero focal lengths, got\n{K}")
    return K


def _rays(K: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``K^-1 (u, v, 1)`` in closed form (z exactly 1), shape ``u.shape + (3,)``."""
    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    y = (v - cy) / fy
    x = (u - cx - s * y) / fx
    return np.stack([x, y, np.ones_like(x)], axis=-1)


def _to_pixels(K: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, 2) pixels of (N, 2) normalised image coordinates ``x / z, y / z``: THE pinhole formula (skew included)."""
    return xy @ K[:2, :2].T + K[:2, 2]


def project_points(K: np.ndarray, X_cam: np.ndarray, *, min_z: float = 1e-9, signed: bool = False) -> np.ndarray:
    """(N, 2) pixel coordinates of camera points (N, 3), unchecked, for inner loops (see :func:`project`).

    Depths below ``min_z`` are raised to ``min_z``, so points on or behind the camera land far outside the image
    (callers filter them by ``z``); ``signed=True`` divides by the signed depth instead and only replaces
    ``|z| <= min_z`` by ``min_z`` (the BOP toolkit's projection, used by MSPD).

    >>> K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    >>> project_points(K, np.array([[0.0, 0, 2], [0.2, -0.1, 1]]))
    array([[32., 24.],
           [52., 14.]])
    >>> project_points(K, np.array([[0.1, 0, -1]]), signed=True)
    array([[22., 24.]])
    """
    K = np.asarray(K, dtype=np.float64)
    X = np.asarray(X_cam, dtype=np.float64)
    z = X[:, 2:3]
    z = np.where(np.abs(z) > min_z, z, min_z) if signed else np.maximum(z, min_z)
    return _to_pixels(K, X[:, :2] / z)


def project(K: np.ndarray, X_cam: np.ndarray, eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points to pixel coordinates (pixel-centre convention).

    Args:
        K: (3, 3) intrinsics.
        X_cam: (N, 3) points in the camera frame, metres.
        eps: points with ``z <= eps`` (metres) are invalid.

    Returns:
        ``(uv (N, 2), valid (N,))``; rows with NaN/inf input, ``z <= eps`` or an
        overflowing projection are NaN with ``valid = False``.
    """
    K = _check_K(K)
    X = as_points(X_cam, 3, "X_cam")
    valid = np.all(np.isfinite(X), axis=1)
    valid &= np.where(valid, X[:, 2], 0.0) > eps
    Xs = np.where(valid[:, None], X, np.array([0.0, 0.0, 1.0]))
    with np.errstate(over="ignore", invalid="ignore"):
        uv = _to_pixels(K, Xs[:, :2] / Xs[:, 2:3])
    valid &= np.all(np.isfinite(uv), axis=1)
    uv[~valid] = np.nan
    return uv, valid


def project_jacobian(K: np.ndarray, X_cam: np.ndarray) -> np.ndarray:
    """(N, 2, 3) derivative of the pinhole projection ``u = fx x / z + cx, v = fy y / z + cy`` with respect
    to the camera-frame point (N, 3) (points with ``z > 0``)."""
    x, y, z = np.asarray(X_cam, dtype=np.float64).T
    iz = 1.0 / z
    du = np.zeros((len(x), 2, 3))
    du[:, 0, 0] = K[0, 0] * iz
    du[:, 0, 2] = -K[0, 0] * x * iz * iz
    du[:, 1, 1] = K[1, 1] * iz
    du[:, 1, 2] = -K[1, 1] * y * iz * iz
    return du


def _scale_rays(rays: np.ndarray, depth: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``rays * depth`` where valid, NaN elsewhere; no warnings."""
    d = np.where(valid, depth, 0.0)
    with np.errstate(over="ignore", invalid="ignore"):
        pts = rays * d[..., None]
    valid = valid & np.all(np.isfinite(pts), axis=-1)
    pts[~valid] = np.nan
    return pts, valid


def backproject(K: np.ndarray, uv: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lift pixels with z-depth to camera-frame points.

    Args:
        K: (3, 3) intrinsics.
        uv: (N, 2) pixel coordinates (pixel-centre convention).
        depth: (N,) z-depth in metres.

    Returns:
        ``(points (N, 3), valid (N,))``; rows with depth <= 0, NaN or inf depth,
        or non-finite ``uv`` are NaN with ``valid = False``.
    """
    K = _check_K(K)
    uv = as_points(uv, 2, "uv")
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != (uv.shape[0],):
        raise InputError(f"depth must have shape ({uv.shape[0]},), got {depth.shape}")
    valid = np.all(np.isfinite(uv), axis=1) & np.isfinite(depth)
    valid &= np.where(valid, depth, 0.0) > 0
    uvs = np.where(valid[:, None], uv, 0.0)
    return _scale_rays(_rays(K, uvs[:, 0], uvs[:, 1]), depth, valid)


def pixel_rays(K: np.ndarray, width: int, height: int, normalize: bool = False) -> np.ndarray:
    """Camera-frame rays through every pixel centre ``(i + 0.5, j + 0.5)``.

    Args:
        K: (3, 3) intrinsics.
        width: image width W in pixels.
        height: image height H in pixels.
        normalize: return unit vectors instead of rays with ``z = 1``.

    Returns:
        (H, W, 3) ray directions.
    """
    K = _check_K(K)
    if int(width) <= 0 or int(height) <= 0:
        raise InputError(f"image size must be positive, got {width}x{height}")
    u, v = np.meshgrid(np.arange(int(width)) + 0.5, np.arange(int(height)) + 0.5)
    rays = _rays(K, u, v)
    return rays / np.linalg.norm(rays, axis=-1, keepdims=True) if normalize else rays


def depth_to_points(K: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Back-project a z-depth image to a camera-frame point map (pixel centres).

    Args:
        K: (3, 3) intrinsics.
        depth: (H, W) z-depth in metres; <= 0, NaN and inf mean "no depth".

    Returns:
        ``(points (H, W, 3), valid (H, W))`` with NaN points where invalid.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise InputError(f"depth must have shape (H, W), got {depth.shape}")
    valid = np.isfinite(depth)
    valid &= np.where(valid, depth, 0.0) > 0
    return _scale_rays(pixel_rays(K, depth.shape[1], depth.shape[0]), depth, valid)


def _focal_shift_inputs(points: np.ndarray, uv: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Flatten to ``(P (N, 3), uv (N, 2))`` keeping rows finite in both."""
    P = np.asarray(points, dtype=np.float64)
    if P.ndim == 3 and P.shape[2] == 3 and uv is None:
        h, w = P.shape[:2]
        u, v = np.meshgrid(np.arange(w) + 0.5 - 0.5 * w, np.arange(h) + 0.5 - 0.5 * h)
        uv = np.stack([u, v], axis=-1)
    if P.shape[-1:] != (3,) or P.ndim not in (2, 3):
        raise InputError(f"points must have shape (H, W, 3) or (N, 3), got {P.shape}")
    if uv is None:
        raise InputError("uv (N, 2) is required when points are given as (N, 3)")
    uv_a = np.asarray(uv, dtype=np.float64)
    P = P.reshape(-1, 3)
    if uv_a.shape[-1:] != (2,) or uv_a.size != 2 * P.shape[0]:
        raise InputError(f"uv must hold one (x, y) per point ({P.shape[0]}), got shape {uv_a.shape}")
    uv_a = uv_a.reshape(-1, 2)
    ok = np.all(np.isfinite(P), axis=1) & np.all(np.isfinite(uv_a), axis=1)
    return P[ok], uv_a[ok]


def _solve_focal_shift(xy: np.ndarray, z: np.ndarray, uv: np.ndarray) -> tuple[float, float, np.ndarray, bool]:
    """Bounded least squares for ``(f, dz)`` on unit-RMS data.

    Returns:
        ``(f, dz, J, on_bound)``: the solution, the (2N, 2) Jacobian there and
        whether it stopped on the ``Z + dz > 0`` bound.
    """
    lb = _MIN_SHIFTED_DEPTH - float(np.min(z))  # Z + dz > 0
    dz0 = 0.0 if lb < 0 else lb + float(np.std(z))  # dz = 0 whenever it is feasible
    p0 = xy / (z + dz0)[:, None]
    x0 = [float(np.sum(p0 * uv) / np.sum(p0 * p0)), dz0]

    def residual(x: np.ndarray) -> np.ndarray:
        return (x[0] * xy / (z + x[1])[:, None] - uv).ravel()

    def jacobian(x: np.ndarray) -> np.ndarray:
        p = xy / (z + x[1])[:, None]
        return np.stack([p.ravel(), (-x[0] * p / (z + x[1])[:, None]).ravel()], axis=1)

    bounds = ([-np.inf, lb], [np.inf, np.inf])
    tols = {"ftol": 1e-15, "xtol": 1e-15, "gtol": 1e-15}
    sol = least_squares(residual, x0, jac=jacobian, bounds=bounds, x_scale="jac", max_nfev=200, **tols)
    return float(sol.x[0]), float(sol.x[1]), jacobian(sol.x), bool(sol.active_mask[1] != 0)


def recover_focal_shift(points: np.ndarray, uv: np.ndarray | None = None, min_points: int = 8) -> tuple[float, float]:
    """Recover the focal length and z-shift of a point map known up to both (GenLaM eq. 1).

    Solves ``min_{f, dz} sum_i |(x_i, y_i) - f (X_i, Y_i) / (Z_i + dz)|^2`` with
    ``scipy.optimize.least_squares`` (analytic Jacobian, ``Z + dz > 0`` enforced
    by a bound), started from the closed-form ``f`` at ``dz = 0``. Points and
    pixels are rescaled to unit RMS first so the problem is well conditioned.
    Non-finite points (masked pixels) are dropped.

    Args:
        points: (H, W, 3) point map or (N, 3) points, in any consistent unit.
        uv: (N, 2) or (H, W, 2) pixel coordinates *relative to the principal
            point*, in pixels. Optional for an (H, W, 3) map: then the principal
            point is the image centre and pixel centres are at ``i + 0.5``.
        min_points: fewest finite points accepted.

    Returns:
        ``(f, dz)``: focal length in pixels and z-shift in the unit of ``points``,
        such that ``(x, y) ~ f (X, Y) / (Z + dz)``.

    Raises:
        InputError: for inconsistent shapes.
        DegenerateGeometryError: for fewer than ``min_points`` finite points,
            all points on the optical axis, all points at (nearly) one depth
            such as a fronto-parallel plane (``f`` and ``dz`` are then
            inseparable: the Jacobian's column-normalised condition is below
            :data:`FOCAL_SHIFT_COND_TOL`), or a solution with ``f <= 0`` or on
            the ``Z + dz > 0`` bound.
    """
    P, uv_a = _focal_shift_inputs(points, uv)
    if P.shape[0] < min_points:
        raise DegenerateGeometryError(f"focal/shift recovery needs >= {min_points} finite points, got {P.shape[0]}")
    s_p = float(np.sqrt(np.mean(np.sum(P * P, axis=1))))
    s_uv = float(np.sqrt(np.mean(np.sum(uv_a * uv_a, axis=1))))
    if s_uv == 0 or not np.sqrt(np.mean(np.sum(P[:, :2] ** 2, axis=1))) > 1e-12 * s_p:
        raise DegenerateGeometryError("all points lie on the optical axis; the focal length is undefined")
    P, uv_a = P / s_p, uv_a / s_uv
    if np.std(P[:, 2]) <= 1e-9:
        raise DegenerateGeometryError("all points have the same depth; focal length and shift are inseparable")
    f, dz, J, on_bound = _solve_focal_shift(P[:, :2], P[:, 2], uv_a)
    if not f > 0 or on_bound:
        raise DegenerateGeometryError(
            f"focal/shift solve gave f={f * s_uv:.4g}, dz={dz * s_p:.4g} (f <= 0 or Z + dz at its lower bound); "
            "the point map does not fit a pinhole camera"
        )
    sv = np.linalg.svd(J / np.linalg.norm(J, axis=0), compute_uv=False)
    if not sv[1] > FOCAL_SHIFT_COND_TOL * sv[0]:
        raise DegenerateGeometryError(
            f"depth varies too little across the point map (condition {sv[1] / sv[0]:.3g}): f and dz are "
            "inseparable, as for a fronto-parallel plane; use a view with depth variation or a known focal"
        )
    return f * s_uv, dz * s_p

"""Rotation representations, conversions and distances (numpy, float64, batched).

Conventions (all functions broadcast over leading dimensions ``...``):

- Rotation matrices act on column vectors, ``x' = R @ x``; shape ``(..., 3, 3)``.
- Quaternions are ``(w, x, y, z)``, scalar first; shape ``(..., 4)``. The
  canonical sign has ``w > 0``; when ``w == 0`` exactly, the first non-zero of
  ``(x, y, z)`` is made positive, so every rotation has one canonical quaternion.
- Axis-angle is the rotation vector ``angle * unit_axis``; shape ``(..., 3)``,
  radians, with ``angle`` in ``[0, pi]``.
- The 6D representation (Zhou et al., "On the Continuity of Rotation
  Representations in Neural Networks", CVPR 2019) is the first two *columns*
  of ``R`` concatenated: ``(R[:, 0], R[:, 1])``; shape ``(..., 6)``.
- Euler angles follow :mod:`scipy.spatial.transform`; they are implemented in
  :mod:`cadalign.geometry.euler` and re-exported here.

Converters propagate NaN rows instead of raising: a row with NaN or inf gives
an all-NaN row, without a RuntimeWarning and without touching the other rows
(a finite row that overflows, ~1e300, is garbage or NaN, also quietly).
Functions whose result is undefined for an input (a zero quaternion, parallel
6D columns) raise :class:`~cadalign.errors.DegenerateGeometryError`.
"""

from __future__ import annotations

import numpy as np

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry._checks import as_batched, nan_rows_where_nonfinite, quiet_nonfinite
from cadalign.geometry.euler import euler_to_matrix, matrix_to_euler

__all__ = [
    "axis_angle_to_matrix",
    "euler_to_matrix",
    "geodesic_angle",
    "is_rotation",
    "matrix_to_axis_angle",
    "matrix_to_euler",
    "matrix_to_quaternion",
    "matrix_to_rotation_6d",
    "orthonormalize",
    "quaternion_angle",
    "quaternion_canonicalize",
    "quaternion_multiply",
    "quaternion_normalize",
    "quaternion_to_matrix",
    "random_rotation",
    "rotation_6d_to_matrix",
    "skew",
]

QUATERNION_NORM_TOL = 1e-12
"""Quaternions with a norm below this are rejected as zero."""

PARALLEL_SIN_TOL = 1e-6
"""6D columns whose angle has ``sin < 1e-6`` (within 5.7e-5 deg of parallel) are rejected."""

_TAYLOR_ANGLE = 1e-4
"""Below this angle (rad) the Rodrigues coefficients use their Taylor series."""


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]_x`` with ``skew(v) @ u == cross(v, u)``.

    Args:
        v: (..., 3) vectors.

    Returns:
        (..., 3, 3) skew-symmetric matrices.
    """
    v = as_batched(v, (3,), "v")
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    o = np.zeros_like(x)
    return np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2)


@quiet_nonfinite
def quaternion_normalize(q: np.ndarray) -> np.ndarray:
    """Scale quaternions ``(..., 4)`` to unit norm.

    Raises:
        DegenerateGeometryError: if any quaternion has norm below
            :data:`QUATERNION_NORM_TOL` (a zero quaternion is no rotation).
    """
    q = as_batched(q, (4,), "q")
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < QUATERNION_NORM_TOL):
        bad = int(np.count_nonzero(n < QUATERNION_NORM_TOL))
        raise DegenerateGeometryError(
            f"{bad} quaternion(s) have norm < {QUATERNION_NORM_TOL:g}; a zero quaternion is not a rotation"
        )
    return nan_rows_where_nonfinite(q / n, (q, 1))


def quaternion_canonicalize(q: np.ndarray) -> np.ndarray:
    """Choose the canonical sign of quaternions ``(..., 4)`` (``q`` and ``-q`` are one rotation).

    The first non-zero component in ``(w, x, y, z)`` order is made positive: so
    ``w > 0`` unless ``w == 0`` exactly, in which case ``x`` decides, then ``y``.
    The norm is left unchanged.
    """
    q = as_batched(q, (4,), "q")
    first = np.argmax(q != 0, axis=-1)
    lead = np.take_along_axis(q, first[..., None], axis=-1)
    # + 0.0 turns a -0.0 component into +0.0 so equal rotations compare equal bitwise
    return q * np.where(lead < 0, -1.0, 1.0) + 0.0


def quaternion_multiply(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Hamilton product ``q1 * q2`` of ``(..., 4)`` wxyz quaternions (rotation ``q2`` first)."""
    q1 = as_batched(q1, (4,), "q1")
    q2 = as_batched(q2, (4,), "q2")
    w1, x1, y1, z1 = np.moveaxis(q1, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(q2, -1, 0)
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        -1,
    )


@quiet_nonfinite
def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` from wxyz quaternions ``(..., 4)`` (normalised first).

    Raises:
        DegenerateGeometryError: for a (near-)zero quaternion.
    """
    w, x, y, z = np.moveaxis(quaternion_normalize(q), -1, 0)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(r, -1) for r in rows], -2)


@quiet_nonfinite
def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Canonical unit wxyz quaternions ``(..., 4)`` from rotation matrices ``(..., 3, 3)``.

    Shepperd's method: the entries of ``R`` give ``4 q q^T`` directly; the row
    with the largest diagonal entry (``4 q_k^2 >= 1``) is divided by its norm, so
    there is no division by a small number for any rotation. Near ``pi`` the
    trace row is small and a diagonal row, built from the *symmetric* part of
    ``R``, is used instead of the vanishing skew part.
    """
    R = as_batched(R, (3, 3), "R")
    r = [[R[..., i, j] for j in range(3)] for i in range(3)]
    tr = r[0][0] + r[1][1] + r[2][2]
    qq = np.stack(
        [
            np.stack([1 + tr, r[2][1] - r[1][2], r[0][2] - r[2][0], r[1][0] - r[0][1]], -1),
            np.stack([r[2][1] - r[1][2], 1 + r[0][0] - r[1][1] - r[2][2], r[0][1] + r[1][0], r[0][2] + r[2][0]], -1),
            np.stack([r[0][2] - r[2][0], r[0][1] + r[1][0], 1 - r[0][0] + r[1][1] - r[2][2], r[1][2] + r[2][1]], -1),
            np.stack([r[1][0] - r[0][1], r[0][2] + r[2][0], r[1][2] + r[2][1], 1 - r[0][0] - r[1][1] + r[2][2]], -1),
        ],
        -2,
    )
    k = np.argmax(np.diagonal(qq, axis1=-2, axis2=-1), axis=-1)
    q = np.take_along_axis(qq, k[..., None, None], axis=-2)[..., 0, :]
    q = quaternion_canonicalize(q / np.linalg.norm(q, axis=-1, keepdims=True))
    return nan_rows_where_nonfinite(q, (R, 2))


@quiet_nonfinite
def axis_angle_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` from rotation vectors ``(..., 3)`` (radians).

    Rodrigues' formula ``R = cos t I + (sin t / t) [w]_x + ((1 - cos t) / t^2) w w^T``
    with Taylor series for ``t < 1e-4`` and ``1 - cos t`` written as
    ``2 sin^2(t/2)`` so no cancellation occurs at any angle.
    """
    w = as_batched(rotvec, (3,), "rotvec")
    t = np.linalg.norm(w, axis=-1)
    small = t < _TAYLOR_ANGLE
    t2 = t * t
    ts = np.where(small, 1.0, t)
    a = np.where(small, 1 - t2 / 6 + t2 * t2 / 120, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, 2 * (np.sin(ts / 2) / ts) ** 2)
    eye = np.broadcast_to(np.eye(3), w.shape[:-1] + (3, 3))
    R = (
        np.cos(t)[..., None, None] * eye
        + a[..., None, None] * skew(w)
        + b[..., None, None] * (w[..., :, None] * w[..., None, :])
    )
    return nan_rows_where_nonfinite(R, (w, 1))


@quiet_nonfinite
def matrix_to_axis_angle(R: np.ndarray) -> np.ndarray:
    """Rotation vectors ``(..., 3)`` (radians, angle in ``[0, pi]``) from matrices ``(..., 3, 3)``.

    Goes through the canonical quaternion ``(w, v)``: ``angle = 2 atan2(|v|, w)``
    and ``rotvec = angle / |v| * v``, with the Taylor series ``2 / w`` of that
    ratio for ``|v| < 1e-6``. Near ``pi`` the axis comes from the symmetric part
    of ``R`` (Shepperd), so it stays accurate; at exactly ``pi`` the sign of the
    axis follows the quaternion tie-break (first non-zero component positive).
    """
    q = matrix_to_quaternion(R)
    w, v = q[..., 0], q[..., 1:]
    s = np.linalg.norm(v, axis=-1)
    small = s < 1e-6
    s_safe = np.where(small, 1.0, s)
    w_safe = np.where(small, w, 1.0)  # w ~ 1 whenever |v| is small
    ratio = np.where(small, 2.0 / w_safe * (1.0 - s * s / (3.0 * w_safe * w_safe)), 2.0 * np.arctan2(s, w) / s_safe)
    return ratio[..., None] * v


@quiet_nonfinite
def rotation_6d_to_matrix(d6: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` from 6D vectors ``(..., 6)`` by Gram-Schmidt.

    Column 0 is ``a1 / |a1|``; column 1 is the part of ``a2`` orthogonal to it
    (projected out twice, so it is orthogonal to ~1e-16 even for nearly
    parallel halves), normalised; column 2 is their cross product. Each half
    may have any scale.

    Raises:
        InputError: if ``d6`` contains NaN or inf.
        DegenerateGeometryError: if either half is zero or the two halves are
            (anti)parallel within ``sin(angle) < PARALLEL_SIN_TOL`` (1e-6).
    """
    d6 = as_batched(d6, (6,), "d6")
    if not np.all(np.isfinite(d6)):
        raise InputError("6D rotation contains NaN or inf")
    a1, a2 = d6[..., :3], d6[..., 3:]
    n1 = np.linalg.norm(a1, axis=-1, keepdims=True)
    n2 = np.linalg.norm(a2, axis=-1, keepdims=True)
    if np.any(n1 == 0) or np.any(n2 == 0):
        raise DegenerateGeometryError("6D rotation has a zero column; the rotation is undefined")
    b1, u2 = a1 / n1, a2 / n2
    sin = np.linalg.norm(np.cross(b1, u2), axis=-1)
    if np.any(sin < PARALLEL_SIN_TOL):
        raise DegenerateGeometryError(
            f"{int(np.count_nonzero(sin < PARALLEL_SIN_TOL))} 6D rotation(s) have (near-)parallel columns "
            f"(sin of their angle < {PARALLEL_SIN_TOL:g}); Gram-Schmidt is undefined"
        )
    b2 = u2 - np.sum(b1 * u2, axis=-1, keepdims=True) * b1
    # one pass leaves b1.b2 ~ 1e-16 / sin (5e-11 at sin = 1e-5); a second pass makes it ~1e-16 ("twice is enough")
    b2 = b2 - np.sum(b1 * b2, axis=-1, keepdims=True) * b1
    b2 = b2 / np.linalg.norm(b2, axis=-1, keepdims=True)
    return np.stack([b1, b2, np.cross(b1, b2)], axis=-1)


def matrix_to_rotation_6d(R: np.ndarray) -> np.ndarray:
    """6D vectors ``(..., 6)``: the first two columns of ``R (..., 3, 3)`` concatenated."""
    R = as_batched(R, (3, 3), "R")
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


@quiet_nonfinite
def geodesic_angle(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Angle (radians, in ``[0, pi]``) of the relative rotation ``R1^T R2``.

    With ``M = R1^T R2``, ``angle = atan2(|vee(M - M^T)| / 2, (trace(M) - 1) / 2)``:
    both arguments are accurate to ~1e-16 absolute, so the angle is accurate
    near 0 *and* near pi, unlike ``arccos((trace - 1) / 2)``.

    Args:
        R1: (..., 3, 3) rotations.
        R2: (..., 3, 3) rotations (broadcast against ``R1``).

    Returns:
        (...) angles in radians.

    >>> Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])  # a quarter turn about z
    >>> float(np.degrees(geodesic_angle(np.eye(3), Rz)))
    90.0
    >>> np.degrees(geodesic_angle(np.eye(3), np.stack([np.eye(3), Rz @ Rz]))).round(6)
    array([  0., 180.])
    """
    R1 = as_batched(R1, (3, 3), "R1")
    R2 = as_batched(R2, (3, 3), "R2")
    M = np.swapaxes(R1, -1, -2) @ R2
    v = np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], -1)
    cos = 0.5 * (M[..., 0, 0] + M[..., 1, 1] + M[..., 2, 2] - 1.0)
    return nan_rows_where_nonfinite(np.arctan2(0.5 * np.linalg.norm(v, axis=-1), cos), (R1, 2), (R2, 2))


@quiet_nonfinite
def quaternion_angle(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Angle (radians, in ``[0, pi]``) between the rotations of quaternions ``(..., 4)``.

    ``2 atan2(|vec(d)|, |w(d)|)`` with ``d = conj(q1) q2``: sign-invariant and
    accurate near 0 and pi. Inputs are normalised first.
    """
    q1 = quaternion_normalize(q1)
    q2 = quaternion_normalize(q2)
    d = quaternion_multiply(q1 * np.array([1.0, -1.0, -1.0, -1.0]), q2)
    return 2.0 * np.arctan2(np.linalg.norm(d[..., 1:], axis=-1), np.abs(d[..., 0]))


def orthonormalize(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius norm) to each ``(..., 3, 3)`` matrix.

    ``U diag(1, 1, det(U V^T)) V^T`` from the SVD ``M = U S V^T``, so a
    reflection is turned into the closest proper rotation.

    Raises:
        InputError: if ``M`` contains NaN or inf.
    """
    M = as_batched(M, (3, 3), "M")
    if not np.all(np.isfinite(M)):
        raise InputError("cannot orthonormalize a matrix containing NaN or inf")
    U, _, Vt = np.linalg.svd(M)
    d = np.where(np.linalg.det(U @ Vt) < 0, -1.0, 1.0)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


@quiet_nonfinite
def is_rotation(R: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Whether each ``(..., 3, 3)`` matrix is finite, orthonormal and has ``det = +1`` within ``tol``.

    Returns:
        (...) boolean array (0-d for a single matrix).
    """
    R = as_batched(R, (3, 3), "R")
    finite = np.all(np.isfinite(R), axis=(-2, -1))
    Rs = np.where(finite[..., None, None], R, np.eye(3))
    ortho = np.max(np.abs(np.swapaxes(Rs, -1, -2) @ Rs - np.eye(3)), axis=(-2, -1)) <= tol
    return finite & ortho & (np.abs(np.linalg.det(Rs) - 1.0) <= tol)


def random_rotation(rng: np.random.Generator, n: int | None = None) -> np.ndarray:
    """Rotations drawn uniformly (Haar measure) from normalised Gaussian quaternions.

    Args:
        rng: the random generator (the only source of randomness).
        n: number of rotations, or ``None`` for a single one.

    Returns:
        (3, 3) if ``n`` is None, else (n, 3, 3).
    """
    shape = (4,) if n is None else (int(n), 4)
    return quaternion_to_matrix(rng.standard_normal(shape))

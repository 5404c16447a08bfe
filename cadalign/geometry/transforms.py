"""SE(3) / Sim(3) helpers on :class:`~cadalign.types.Rigid3`, :class:`~cadalign.types.Sim3`
or homogeneous ``(4, 4)`` matrices.

Naming follows :mod:`cadalign.types`: ``T_a_from_b`` maps points in frame ``b``
to frame ``a``; composition ``compose(T_a_from_b, T_b_from_c) -> T_a_from_c``.
Units are metres and radians.
"""

from __future__ import annotations

import numpy as np

from cadalign.errors import InputError
from cadalign.geometry._checks import as_points
from cadalign.geometry.rotations import geodesic_angle, orthonormalize
from cadalign.types import Rigid3, Sim3

Transform = Rigid3 | Sim3 | np.ndarray
"""A rigid or similarity transform: a dataclass or a (4, 4) homogeneous matrix."""

SIM3_ORTHO_TOL = 1e-6
"""Largest ``|(A/s)^T (A/s) - I|`` entry accepted when decomposing a matrix as a Sim3."""


def sim3_from_matrix(M: np.ndarray, tol: float = SIM3_ORTHO_TOL) -> Sim3:
    """Decompose a homogeneous similarity matrix ``[[s R, t], [0, 1]]``.

    The scale is ``det(A)^(1/3)`` of the upper-left block ``A``; ``A / s`` must be
    orthonormal within ``tol`` and is then projected onto SO(3) (SVD) so small
    rounding is cleaned up.

    Args:
        M: (4, 4) matrix.
        tol: orthonormality tolerance of ``A / s``.

    Returns:
        The :class:`Sim3`.

    Raises:
        InputError: if ``M`` is not (4, 4), has NaN/inf, a bottom row other than
            ``(0, 0, 0, 1)``, ``det(A) <= 0`` (a reflection or a singular map, so no
            positive scale), a non-finite scale, or shear / anisotropic scale.
    """
    M = np.asarray(M, dtype=np.float64)
    if M.shape != (4, 4):
        raise InputError(f"expected a (4, 4) homogeneous matrix, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise InputError("homogeneous matrix contains NaN or inf")
    if not np.array_equal(M[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"bottom row of a similarity must be (0, 0, 0, 1), got {M[3]}")
    A = M[:3, :3]
    # slogdet: det itself over/underflows for scales beyond ~1e+-100 (a valid, if extreme, similarity)
    sign, logdet = np.linalg.slogdet(A)
    if not (sign > 0 and np.isfinite(logdet)):
        raise InputError(f"det of the linear part is {sign * np.exp(logdet):g} <= 0: no positive scale "
                         "(reflection or singular)")
    s = float(np.exp(logdet / 3.0))
    if not np.isfinite(s) or s <= 0:
        raise InputError(f"scale det^(1/3) = {s:g} is not finite and positive")
    R = A / s
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > tol:
        raise InputError(f"linear part is not a scaled rotation (orthonormality error {err:.3g} > {tol:g})")
    return Sim3(s, orthonormalize(R), M[:3, 3])


def _as_sim3(T: Transform) -> Sim3:
    if isinstance(T, Sim3):
        return T
    if isinstance(T, Rigid3):
        return Sim3.from_rigid(T)
    return sim3_from_matrix(T)


def compose(T_a_from_b: Transform, T_b_from_c: Transform) -> Transform:
    """Compose two transforms: ``T_a_from_c = T_a_from_b o T_b_from_c``.

    Returns a ``(4, 4)`` matrix if either input is a matrix, a :class:`Sim3` if
    either is a Sim3, else a :class:`Rigid3`.
    """
    if isinstance(T_a_from_b, Rigid3) and isinstance(T_b_from_c, Rigid3):
        return T_a_from_b @ T_b_from_c
    out = _as_sim3(T_a_from_b) @ _as_sim3(T_b_from_c)
    if isinstance(T_a_from_b, np.ndarray) or isinstance(T_b_from_c, np.ndarray):
        return out.matrix()
    return out


def invert(T: Transform) -> Transform:
    """Inverse transform, exact in closed form (no general matrix inverse).

    Returns the same kind as the input: ``Rigid3``, ``Sim3`` or ``(4, 4)`` matrix.

    Raises:
        InputError: for a matrix that is not a similarity (see :func:`sim3_from_matrix`).
    """
    if isinstance(T, Rigid3 | Sim3):
        return T.inverse()
    return sim3_from_matrix(T).inverse().matrix()


def transform_points(T: Transform, points: np.ndarray) -> np.ndarray:
    """Apply ``T_a_from_b`` to points ``(N, 3)`` in frame ``b``; returns ``(N, 3)`` in frame ``a``.

    Raises:
        InputError: for points not shaped (N, 3) or a matrix that is not a similarity.
    """
    pts = as_points(points, 3, "points")
    if isinstance(T, Rigid3):
        return T.apply(pts)
    return _as_sim3(T).apply(pts)


def relative_pose_error(T_est: Transform, T_gt: Transform) -> tuple[float, float]:
    """Rotation and translation error between an estimated and a true pose ``T_a_from_b``.

    ``rot_rad`` is the geodesic angle between the rotations (radians) and
    ``trans_m`` is ``|t_est - t_gt|`` in frame ``a`` (metres); equivalently the
    translation of ``T_gt^-1 o T_est`` for rigid poses. Scales of Sim3 inputs
    are ignored: compare ``T.s`` separately.

    Returns:
        ``(rot_rad, trans_m)``.
    """
    est, gt = _as_sim3(T_est), _as_sim3(T_gt)
    return float(geodesic_angle(est.R, gt.R)), float(np.linalg.norm(est.t - gt.t))

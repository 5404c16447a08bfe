"""Euler angles <-> rotation matrices for all 12 axis sequences (numpy, float64, batched).

Sequences are written as in :mod:`scipy.spatial.transform`: three letters from
``xyz`` with no two consecutive letters equal. Lowercase is *extrinsic*
(rotations about the fixed axes, in order: ``"xyz"`` gives
``R = Rz(c) @ Ry(b) @ Rx(a)``), uppercase is *intrinsic* (about the moving
axes: ``"XYZ"`` gives ``R = Rx(a) @ Ry(b) @ Rz(c)``). Tait-Bryan sequences
(three distinct axes) return ``b`` in ``[-pi/2, pi/2]``; proper Euler sequences
(first axis repeated) return ``b`` in ``[0, pi]``; ``a`` and ``c`` are in
``(-pi, pi]``.

At gimbal lock (``|cos b| < GIMBAL_TOL`` for Tait-Bryan, ``|sin b| <
GIMBAL_TOL`` for proper Euler) only a sum or difference of ``a`` and ``c`` is
determined; like scipy we then set the third angle ``c`` to exactly 0 (without
a warning). Setting ``c = 0`` while ``b`` is off the lock by ``delta`` costs a
rotation error of at most ``2 delta``, so the matrix round trip is within
``2 * GIMBAL_TOL`` (2e-12 rad) at and near the lock and ~1e-15 rad elsewhere.
Euler angles belong at I/O boundaries only; use matrices, quaternions or 6D
internally.
"""

from __future__ import annotations

import numpy as np

from cadalign.errors import InputError
from cadalign.geometry._checks import as_batched, nan_rows_where_nonfinite, quiet_nonfinite

GIMBAL_TOL = 1e-12
"""Below this ``|cos b|`` (Tait-Bryan) or ``|sin b|`` (proper) the third angle is set to 0.

Small, because the general branch stays exact arbitrarily close to the lock
(the residual absorbs the error of ``a``) while the lock branch is off by up
to ``2 * GIMBAL_TOL`` rad; large enough to catch an exact lock blurred by
rounding (~1e-16 per entry)."""

_AXIS = {"x": 0, "y": 1, "z": 2}


def _parse_seq(seq: str) -> tuple[tuple[int, int, int], bool]:
    """Axis indices and ``intrinsic`` flag of a scipy-style sequence string."""
    if (
        not isinstance(seq, str)
        or len(seq) != 3
        or not (seq.islower() or seq.isupper())
        or any(ch not in _AXIS for ch in seq.lower())
    ):
        raise InputError(f"Euler sequence must be 3 letters from 'xyz' (extrinsic) or 'XYZ' (intrinsic), got {seq!r}")
    i, j, k = (_AXIS[ch] for ch in seq.lower())
    if i == j or j == k:
        raise InputError(f"Euler sequence {seq!r} repeats an axis consecutively; use e.g. 'xyz' or 'zxz'")
    return (i, j, k), seq.isupper()


def _axis_rotation(m: int, theta: np.ndarray) -> np.ndarray:
    """Rotation by ``theta (...)`` about coordinate axis ``m``, shape ``(..., 3, 3)``."""
    p, q = (m + 1) % 3, (m + 2) % 3
    c, s = np.cos(theta), np.sin(theta)
    R = np.zeros(np.shape(theta) + (3, 3))
    R[..., m, m] = 1.0
    R[..., p, p] = c
    R[..., q, q] = c
    R[..., q, p] = s
    R[..., p, q] = -s
    return R


def _angle_about(M: np.ndarray, m: int) -> np.ndarray:
    """Angle of ``M (..., 3, 3)``, assumed a rotation about axis ``m``, from its 2x2 block."""
    p, q = (m + 1) % 3, (m + 2) % 3
    return np.arctan2(M[..., q, p] - M[..., p, q], M[..., p, p] + M[..., q, q])


def _intrinsic_angles(R: np.ndarray, axes: tuple[int, int, int], zero_first: bool) -> tuple[np.ndarray, ...]:
    """Angles ``(a, b, c)`` with ``R = R_i(a) R_j(b) R_m(c)``.

    ``b`` and (away from the lock) ``a`` come from one column of ``R``; ``c`` is
    then read from the residual ``R_j(b)^T R_i(a)^T R``, which absorbs the error
    of ``a`` when ``b`` is close to the lock, so the matrix round trip stays at
    ~1e-15 everywhere. At the lock, ``c = 0`` (or ``a = 0`` when ``zero_first``)
    and the other angle is read from the residual.
    """
    i, j, m = axes
    k = 3 - i - j  # the axis not among the first two
    eps = 1.0 if (j - i) % 3 == 1 else -1.0  # parity of (i, j, k)
    if i == m:  # proper Euler: column i is (cos b, sin b sin a, -eps sin b cos a) on (i, j, k)
        sin_b = np.hypot(R[..., j, i], R[..., k, i])
        b = np.arctan2(sin_b, R[..., i, i])
        a = np.arctan2(R[..., j, i], -eps * R[..., k, i])
        lock = sin_b < GIMBAL_TOL
    else:  # Tait-Bryan: column k is (eps sin b, -eps cos b sin a, cos b cos a) on (i, j, k)
        cos_b = np.hypot(R[..., j, k], R[..., k, k])
        b = np.arctan2(eps * R[..., i, k], cos_b)
        a = np.arctan2(-eps * R[..., j, k], R[..., k, k])
        lock = cos_b < GIMBAL_TOL
    Rj_t = np.swapaxes(_axis_rotation(j, b), -1, -2)
    if zero_first:
        a = np.where(lock, 0.0, a)
    else:  # with c = 0, R R_j(b)^T = R_i(a)
        a = np.where(lock, _angle_about(R @ Rj_t, i), a)
    c = _angle_about(Rj_t @ np.swapaxes(_axis_rotation(i, a), -1, -2) @ R, m)
    if not zero_first:
        c = np.where(lock, 0.0, c)
    return a, b, c


@quiet_nonfinite
def euler_to_matrix(angles: np.ndarray, seq: str) -> np.ndarray:
    """Rotation matrices from Euler angles.

    Args:
        angles: (..., 3) angles in radians, in the order of ``seq``.
        seq: one of the 12 sequences, lowercase extrinsic or uppercase
            intrinsic (scipy convention, see the module docstring).

    Returns:
        (..., 3, 3) rotation matrices.

    Raises:
        InputError: for an invalid sequence or shape.
    """
    (i, j, k), intrinsic = _parse_seq(seq)
    angles = as_batched(angles, (3,), "angles")
    Ra, Rb, Rc = (_axis_rotation(ax, angles[..., n]) for n, ax in enumerate((i, j, k)))
    return nan_rows_where_nonfinite(Ra @ Rb @ Rc if intrinsic else Rc @ Rb @ Ra, (angles, 1))


@quiet_nonfinite
def matrix_to_euler(R: np.ndarray, seq: str) -> np.ndarray:
    """Euler angles from rotation matrices, exact at and near gimbal lock.

    Args:
        R: (..., 3, 3) rotation matrices.
        seq: one of the 12 sequences (scipy convention, see the module docstring).

    Returns:
        (..., 3) angles in radians, in the order of ``seq``. At gimbal lock the
        third angle is 0 and the first carries the whole free rotation; the
        returned angles reproduce ``R`` to ~1e-15 rad, and to within
        ``2 * GIMBAL_TOL`` (2e-12 rad) at and near gimbal lock.

    Raises:
        InputError: for an invalid sequence or shape.
    """
    axes, intrinsic = _parse_seq(seq)
    R = as_batched(R, (3, 3), "R")
    if intrinsic:
        a, b, c = _intrinsic_angles(R, axes, zero_first=False)
    else:
        # extrinsic (i, j, k) with (a, b, c) is intrinsic (k, j, i) with (c, b, a)
        c, b, a = _intrinsic_angles(R, axes[::-1], zero_first=True)
    return nan_rows_where_nonfinite(np.stack([a, b, c], axis=-1), (R, 2))

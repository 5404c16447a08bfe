"""Shared pieces of the pose refinements (:mod:`cadalign.infer.refine`): the twist update of a pose, the
projection Jacobian, Huber weights, the damped Gauss-Newton solve and the Gaussian prior on the deviation from
the detector's pose.

A pose is updated by ``(omega, v)`` (:func:`apply_twist`): a turn about the object's origin in camera axes and
a shift. A point moves as ``X' = X + omega x (X - t) + v``; its projection's Jacobian is ``du/dX [-[X - t]_x, I]``.
"""

from __future__ import annotations

import numpy as np

from cadalign.geometry.camera import project_jacobian
from cadalign.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle
from cadalign.infer.config import RefineConfig
from cadalign.infer.model_geom import ModelGeometry
from cadalign.types import Rigid3


def apply_twist(xi: np.ndarray, T: Rigid3) -> Rigid3:
    """The pose turned by ``omega`` about the object's origin (camera axes) and moved by ``v``: ``xi = (omega, v)``.

    ``R' = exp(omega) R``, ``t' = t + v``. Turning about the object rather than the camera keeps rotation and
    translation decoupled for a part many metres away (a camera-centred twist couples them by the distance).
    """
    dR = axis_angle_to_matrix(np.asarray(xi[:3], float))
    return Rigid3(dR @ T.R, T.t + np.asarray(xi[3:], float))


def proj_jacobian(K: np.ndarray, X: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 2, 6) Jacobian of the projection of camera points X (N, 3) wrt ``(omega, v)`` of :func:`apply_twist`.

    A point moves as ``X' = X + omega x (X - t) + v`` with ``t`` the object's origin in the camera frame.
    """
    a, b, c = (X - t).T
    du = project_jacobian(K, X)
    dX = np.zeros((len(X), 3, 6))
    dX[:, 0, 1], dX[:, 0, 2] = c, -b  # -[X - t]_x
    dX[:, 1, 0], dX[:, 1, 2] = -c, a
    dX[:, 2, 0], dX[:, 2, 1] = b, -a
    dX[:, :, 3:] = np.eye(3)
    return du @ dX


def small_step(step: np.ndarray, cfg: RefineConfig, geom: ModelGeometry) -> bool:
    """True when the update's rotation (rad) and translation / diameter are both below ``cfg.min_step``."""
    return bool(np.linalg.norm(step[:3]) < cfg.min_step and np.linalg.norm(step[3:]) < cfg.min_step * geom.diameter_m)


def clamp_step(step: np.ndarray, diameter_m: float) -> np.ndarray:
    """Limit updates ``(..., 6)`` to 0.2 rad and a quarter diameter each (a guard against a near-singular system)."""
    out = np.array(step, dtype=float)
    for sl, lim in ((slice(0, 3), 0.2), (slice(3, 6), 0.25 * diameter_m)):
        n = np.linalg.norm(out[..., sl], axis=-1, keepdims=True)
        out[..., sl] *= np.minimum(1.0, lim / np.maximum(n, 1e-300))
    return out


def huber_weights(r: np.ndarray, k: float) -> np.ndarray:
    """IRLS weights of the Huber loss with threshold ``k`` for residuals ``r`` (1 inside, ``k / |r|`` beyond)."""
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def solve_step(J: np.ndarray, r: np.ndarray, w: np.ndarray, damping: float) -> np.ndarray | None:
    """Weighted damped Gauss-Newton step ``argmin sum w (r + J xi)^2``; None when under-determined."""
    if len(r) < 6:
        return None
    Jw = J * w[:, None]
    H = Jw.T @ J
    g = Jw.T @ r
    H += damping * np.mean(np.diag(H)) * np.eye(6)
    try:
        return -np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        return None


def pose_prior(T: Rigid3, T_init: Rigid3, cfg: RefineConfig, unit: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows (r (6,), J (6, 6)) of the Gaussian prior on the deviation from the detector's pose.

    The deviation is (rotation vector of ``R R_init^T``, ``t - t_init``); a step (omega, v) of
    :func:`apply_twist` changes it by (omega, v) to first order. Scaled by ``unit / sigma``: one sigma costs as
    much as one residual of size ``unit`` (the Huber threshold), negligible where the data constrain the pose,
    decisive where they do not (depth of a small silhouette, the axis of a cylinder in ICP).
    """
    dev = np.concatenate([matrix_to_axis_angle(T.R @ T_init.R.T), T.t - T_init.t])
    S = np.diag([unit / np.radians(cfg.prior_r_deg)] * 3 + [unit / cfg.prior_t_m] * 3)
    return S @ dev, S

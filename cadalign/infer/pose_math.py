"""Pose arithmetic of the temporal fusion and the camera registration on static parts (below both modules).

``canonicalize`` picks a symmetric part's equivalent pose nearest a reference rotation, ``robust_mean`` is the
Huber-IRLS mean of poses, and ``twist_between`` / ``apply_twist_camera`` are the left SE(3) twist between two
poses and its application.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cadalign.cad.symmetry import Symmetry, rotation_about_line
from cadalign.geometry.rotations import (
    axis_angle_to_matrix,
    geodesic_angle,
    matrix_to_axis_angle,
    orthonormalize,
    skew,
)
from cadalign.infer.refine.refine_math import huber_weights
from cadalign.types import Rigid3


@dataclass(frozen=True)
class Observation:
    """One refined detection of a frame."""

    label: int
    T_cam_from_obj: Rigid3
    obj_id: int | None = None
    symmetry: Symmetry = field(default_factory=Symmetry.none)
    diameter_m: float = 0.0
    id_px: int = 0
    """Mask pixels of the detection when its model was chosen by identification here (0: carried by a track or
    a box of the previous frame, or given): the evidence its track's model rests on."""



def canonicalize(T: Rigid3, symmetry: Symmetry | None, R_ref: np.ndarray) -> Rigid3:
    """The symmetric equivalent ``T @ S`` whose rotation is closest (geodesic) to ``R_ref`` (3, 3)."""
    if symmetry is None or symmetry.kind == "none":
        return T
    M0 = T.matrix()
    best, best_ang = T, math.inf
    for D in [np.eye(4), *symmetry.discrete]:
        S = D
        if symmetry.kind == "continuous":
            a = np.asarray(symmetry.axis, float)
            N = D[:3, :3] @ R_ref.T @ T.R  # maximise trace(N Rot(a, th)) = A cos th + B sin th + const
            A = np.trace(N) - a @ N @ a
            B = np.trace(N @ skew(a))
            S = rotation_about_line(a, np.asarray(symmetry.offset_m, float), math.atan2(B, A)) @ D
        cand = Rigid3.from_matrix(M0 @ S)
        ang = float(geodesic_angle(R_ref, cand.R))
        if ang < best_ang - 1e-12:
            best, best_ang = cand, ang
    return best


def robust_mean(poses: list[Rigid3], huber_t_m: float, huber_r_rad: float, iters: int = 5) -> Rigid3:
    """Huber-IRLS mean of rigid poses: weighted translation mean and chordal rotation mean (SVD projection)."""
    t = np.array([p.t for p in poses])
    Rs = np.array([p.R for p in poses])
    mu_t, mu_R = np.median(t, axis=0), orthonormalize(Rs.mean(axis=0))
    for _ in range(iters):
        dt = np.linalg.norm(t - mu_t, axis=1)
        dr = geodesic_angle(mu_R, Rs)
        wt, wr = huber_weights(dt, huber_t_m), huber_weights(dr, huber_r_rad)
        mu_t = (wt[:, None] * t).sum(0) / wt.sum()
        mu_R = orthonormalize((wr[:, None, None] * Rs).sum(0))
    return Rigid3(mu_R, mu_t)


def twist_between(T_from: Rigid3, T_to: Rigid3) -> np.ndarray:
    """The left twist ``xi`` with ``apply_twist(xi, T_from) == T_to`` (rotation vector exact)."""
    dR = T_to.R @ T_from.R.T
    return np.concatenate([matrix_to_axis_angle(dR), T_to.t - dR @ T_from.t])


def apply_twist_camera(xi: np.ndarray, T: Rigid3) -> Rigid3:
    """``T`` moved by the left twist ``xi = (omega, v)`` about the camera origin: ``R' = exp(omega) R``,
    ``t' = exp(omega) t + v`` (the inverse of :func:`twist_between`;
    :func:`cadalign.infer.refine.refine_math.apply_twist` turns about the object instead)."""
    dR = axis_angle_to_matrix(np.asarray(xi[:3], float))
    return Rigid3(dR @ T.R, dR @ T.t + np.asarray(xi[3:], float))

"""Yaw restarts for refinement and model identification that a part's symmetry does not make redundant.

A network unsure of an upright part's yaw (a valve on a frame) is often wrong by more than ICP's basin
(~30 deg), so refinement restarts from the pose turned about the model's z axis. For a part invariant to a
half turn about z (the default scene's valves), turns of 0 and 180 deg are the same pose: four restarts at
multiples of 90 deg are only two distinct ones, 90 deg apart, and a 45-65 deg yaw error stays out of reach
(measured on the held-out valves of a 1800-step network, /work/runs_shared/pose7c/RESULTS.md). Spreading the
restarts over the turn that the symmetry leaves distinct (180 deg for a half-turn symmetry) gives four distinct
starts 45 deg apart.
"""

from __future__ import annotations

import math

import numpy as np

from cadalign.cad.symmetry import Symmetry

_Z = np.array([0.0, 0.0, 1.0])


def yaw_period_rad(symmetry: Symmetry | None, tol_deg: float = 1.0) -> float:
    """The smallest positive turn about the model's z axis (through the origin) the part is invariant to.

    ``2 pi`` when the symmetry has no such turn, 0 for a continuous symmetry about z (every yaw is the same pose).
    A symmetry transform counts when its rotation keeps z (within ``tol_deg``); its translation is ignored, the
    refinement only needs the angle.
    """
    if symmetry is None or symmetry.kind == "none":
        return 2 * math.pi
    if symmetry.kind == "continuous" and symmetry.axis is not None and abs(float(symmetry.axis @ _Z)) > math.cos(
            math.radians(tol_deg)):
        return 0.0
    best = 2 * math.pi
    for T in symmetry.discrete:
        R = np.asarray(T)[:3, :3]
        if float(R[:, 2] @ _Z) < math.cos(math.radians(tol_deg)):
            continue  # this turn moves the z axis
        angle = math.atan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1]) % (2 * math.pi)
        if math.radians(tol_deg) < angle < 2 * math.pi - math.radians(tol_deg):
            best = min(best, angle, 2 * math.pi - angle)
    return best


def yaw_hypotheses_rad(n: int, symmetry: Symmetry | None = None) -> list[float]:
    """``n`` restart yaws (the first 0) spread evenly over the model's distinct yaw range (:func:`yaw_period_rad`).

    A part invariant to every yaw gets only the detector's pose ([0.0]).
    """
    period = yaw_period_rad(symmetry)
    if n <= 1 or period == 0.0:
        return [0.0]
    return [period * k / n for k in range(n)]

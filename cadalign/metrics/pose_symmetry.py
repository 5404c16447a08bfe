"""Finding the rotational symmetries a CAD model has but its ``models_info.json`` may not declare.

A pose error of 180 deg about an axis the part is (nearly) invariant to is no error: the image cannot tell
the two poses apart, a network trained without that symmetry is pulled towards the mean of both, and a
metric without it reports the flip. :func:`undeclared_symmetries` tests the usual candidates (half and
quarter turns about the model axes, through the model origin) by the largest distance from each rotated
model point to the nearest model point (BOP's MSSD between the identity and the candidate; with mesh vertices
as the points, as BOP's metrics use them, a symmetric mesh maps its vertices onto each other).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from cadalign.cad.symmetry import Symmetry, axis_angle_matrix

log = logging.getLogger(__name__)


CANDIDATES: dict[str, np.ndarray] = {f"R{a}{d}": axis_angle_matrix(np.eye(3)["xyz".index(a)], np.radians(d))
                                      for a in "xyz" for d in (180, 90)}
"""Candidate symmetries: half and quarter turns about the model's x, y and z axes (through its origin)."""


@dataclass(frozen=True)
class SymmetryFinding:
    """One candidate rotation a model is invariant to: its name, (3, 3) matrix and deviation in diameters."""

    name: str
    R: np.ndarray
    max_dev: float


def symmetry_deviation(points_m: np.ndarray, R: np.ndarray, diameter_m: float) -> float:
    """Largest distance from each rotated point ``R p`` to the nearest point ``(N, 3)``, in model diameters.

    With dense surface samples this is the MSSD between the identity and ``R`` (plus the sampling spacing).
    """

    pts = np.asarray(points_m, dtype=np.float64)
    return float(cKDTree(pts).query(pts @ np.asarray(R, float).T)[0].max() / max(diameter_m, 1e-12))


def undeclared_symmetries(points_m: np.ndarray, diameter_m: float, declared: Symmetry, tol: float = 0.025
                          ) -> list[SymmetryFinding]:
    """Candidate rotations the model is invariant to within ``tol`` diameters that ``declared`` does not cover.

    Args:
        points_m: (N, 3) dense surface samples in the model frame (a few thousand or more: the sampling
            spacing adds to the deviation).
        diameter_m: the model diameter.
        declared: the symmetry the model declares.
        tol: largest deviation (fraction of the diameter) still called a symmetry.
    """
    have = [T[:3, :3] for T in declared.discretize(360)]
    out = []
    for name, R in CANDIDATES.items():
        if any(np.degrees(np.arccos(np.clip((np.trace(S.T @ R) - 1) / 2, -1, 1))) < 1.0 for S in have):
            continue
        dev = symmetry_deviation(points_m, R, diameter_m)
        if dev <= tol:
            out.append(SymmetryFinding(name, R, dev))
    return out


def warn_undeclared(models: dict[int, tuple[np.ndarray, float, Symmetry]], tol: float = 0.025) -> dict[int, list[str]]:
    """Log a warning per model with undeclared symmetries; returns obj_id -> candidate names (only those with any)."""
    found = {}
    for oid, (pts, diam, sym) in sorted(models.items()):
        names = [f.name for f in undeclared_symmetries(pts, diam, sym, tol)]
        if names:
            found[oid] = names
            log.warning("model %d is invariant to %s within %.0f%% of its diameter but declares no such symmetry: "
                        "pose errors of those turns are counted (declare it in the scene spec / models_info.json)",
                        oid, ", ".join(names), 100 * tol)
    return found

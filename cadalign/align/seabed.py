"""The seabed under the structure, from the SfM points that are not on the CAD, as an occluder.

Subsea structures stand on the seabed and are often partly sunk into it (mud mats, piles, the bottom of a
frame). The CAD knows nothing of that: ray-cast alone, the buried part would show in the visible masks
and its outline would be matched against sediment in the edge alignment. SfM, however, reconstructs the
seabed around the structure. This module fits a plane to the aligned SfM points near the structure's
footprint that are not on the CAD (RANSAC, then least squares on the inliers), checks that it is a floor
(every camera above it, the structure's centre above it, the plane not far below the structure), and
returns a square of it as background geometry (instance 0: it occludes, it gets no mask and no depth).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from cadalign.errors import DegenerateGeometryError
from cadalign.geometry.plane import fit_plane
from cadalign.raycast.core import MeshQuery

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SeabedConfig:
    enabled: bool = True
    """Look for a seabed plane and use it as an occluder (off: the CAD alone is ray cast)."""
    off_cad_m: float = 0.05
    """SfM points farther than this from the CAD are seabed candidates, metres."""
    radius: float = 0.75
    """Candidates within this many CAD bounding-box diagonals of the CAD's centre (horizontally) are used;
    the occluder square has this half-size too."""
    inlier_m: float = 0.05
    """A candidate within this distance of the plane supports it, metres."""
    min_points: int = 40
    """Fewer supporting points: no seabed."""
    min_fraction: float = 0.4
    """A plane supported by less than this fraction of the candidates is no seabed."""
    max_gap: float = 0.25
    """The plane may lie at most this many CAD diagonals below the CAD's lowest point."""
    iterations: int = 300
    """RANSAC iterations."""
    seed: int = 0
    """RANSAC seed (the result is deterministic)."""


@dataclass(frozen=True)
class Seabed:
    """A plane ``n . x = d`` (unit ``n`` towards the cameras) and its occluder square (world, metres)."""

    normal: np.ndarray
    offset: float
    vertices: np.ndarray
    faces: np.ndarray
    summary: dict[str, Any]


def _ransac_plane(P: np.ndarray, inlier_m: float, iterations: int, seed: int) -> tuple[np.ndarray, float, np.ndarray]:
    rng = np.random.default_rng(seed)
    best = np.zeros(len(P), dtype=bool)
    for _ in range(iterations):
        a, b, c = P[rng.choice(len(P), 3, replace=False)]
        n = np.cross(b - a, c - a)
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        inl = np.abs(P @ n - n @ a) < inlier_m
        if inl.sum() > best.sum():
            best = inl
    if best.sum() < 3:
        return np.array([0.0, 0.0, 1.0]), 0.0, best
    for _ in range(2):  # least squares on the inliers, then re-select
        try:
            plane = fit_plane(P[best])
        except DegenerateGeometryError:  # collinear inliers: keep the RANSAC selection
            break
        n, c = plane.normal, plane.centroid
        best = np.abs((P - c) @ n) < inlier_m
        if best.sum() < 3:
            break
    return n, float(n @ c), best


def fit_seabed(points_m: np.ndarray, dist_to_cad_m: np.ndarray, cad_vertices_m: np.ndarray,
               camera_centres_m: np.ndarray, cfg: SeabedConfig) -> Seabed | None:
    """The seabed under the CAD from aligned SfM points (world metres) and their distances to the CAD;
    None when off, or when no plane passes the checks (the reason is logged)."""
    if not cfg.enabled or len(points_m) < 3 or len(cad_vertices_m) == 0:
        return None
    lo, hi = cad_vertices_m.min(axis=0), cad_vertices_m.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    centre = (lo + hi) / 2
    cand = points_m[(dist_to_cad_m > cfg.off_cad_m) & np.all(np.isfinite(points_m), axis=1)]
    # near the footprint; "horizontal" is not known yet, so first a sphere, then the plane's own distance
    cand = cand[np.linalg.norm(cand - centre, axis=1) < (cfg.radius + 0.5) * diag]
    if len(cand) < cfg.min_points:
        log.info("no seabed: %d SfM points off the CAD near it (need %d)", len(cand), cfg.min_points)
        return None
    n, d, inl = _ransac_plane(cand, cfg.inlier_m, cfg.iterations, cfg.seed)
    if np.mean(camera_centres_m @ n - d) < 0:
        n, d = -n, -d
    above_cams = float(np.mean(camera_centres_m @ n - d > cfg.inlier_m))
    lowest = float(np.min(cad_vertices_m @ n - d))
    summary = {"candidates": len(cand), "inliers": int(inl.sum()), "fraction": float(inl.mean()),
               "normal": n.tolist(), "offset_m": d, "cameras_above": above_cams, "cad_lowest_above_m": lowest,
               "cad_centre_above_m": float(centre @ n - d)}
    reasons = []
    if inl.sum() < cfg.min_points or inl.mean() < cfg.min_fraction:
        reasons.append(f"only {int(inl.sum())} of {len(cand)} points on one plane")
    if above_cams < 1.0:
        reasons.append(f"{100 * (1 - above_cams):.0f} % of the cameras are not above it")
    if centre @ n - d <= 0:
        reasons.append("the CAD's centre is below it")
    if lowest > cfg.max_gap * diag:
        reasons.append(f"it lies {lowest:.2f} m below the CAD")
    if reasons:
        log.info("no seabed: %s", "; ".join(reasons))
        return None
    # the occluder: a square of the plane round the CAD centre's foot
    foot = centre - (centre @ n - d) * n
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    h = cfg.radius * diag
    verts = np.array([foot + h * (su * u + sv * v) for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    log.info("seabed: %d of %d points on a plane %.2f m under the CAD's centre; %.2f m of the CAD below it",
             int(inl.sum()), len(cand), summary["cad_centre_above_m"], max(-lowest, 0.0))
    return Seabed(n, d, verts, faces, summary)


def seabed_from_model(rec: Any, cad_from_sfm: Any, cad_vertices_m: np.ndarray, cad_faces: np.ndarray,
                      cfg: SeabedConfig) -> Seabed | None:
    """:func:`fit_seabed` on a ``pycolmap.Reconstruction`` aligned by ``cad_from_sfm`` (a Sim3)."""
    if not cfg.enabled:
        return None

    xyz = np.array([p.xyz for p in rec.points3D.values()], dtype=np.float64).reshape(-1, 3)
    P = cad_from_sfm.apply(xyz) if len(xyz) else xyz
    dist = MeshQuery(cad_vertices_m, cad_faces).distances(P)
    centres = []
    for im in rec.images.values():
        if im.has_pose:
            centres.append(cad_from_sfm.apply(np.asarray(im.projection_center())[None])[0])
    return fit_seabed(P, dist, cad_vertices_m, np.array(centres).reshape(-1, 3), cfg)

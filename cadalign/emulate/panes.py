"""Planar panes (GenLaM, Algorithm 1): a mask of flat regions -> one convex planar polygon per region.

For each connected component of the mask: sample its perimeter pixels, lift them to 3D with the depth,
fit a plane by SVD (:func:`cadalign.geometry.fit_plane`: normal facing the camera, coincident or collinear
points rejected), project the points into the plane, take their 2D convex hull
(:func:`cadalign.geometry.convex_hull_2d`) and fan-triangulate it (:func:`cadalign.geometry.fan_triangulate`).
Only the perimeter is used because depth inside glass, screens or water surfaces is unreliable (the depth
sees through or reflects); the rim is where the pane meets solid structure.

Components too small, without enough valid depth, degenerate (a pixel, a line) or not planar (RMS
residual above ``max_rms_rel`` times their mean depth) are skipped and reported in
:attr:`PaneResult.rejected` with the reason; nothing raises for a degenerate mask.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from cadalign.config import bounded
from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry import (
    Plane,
    convex_hull_2d,
    fan_triangulate,
    fit_plane,
    lift_from_plane_2d,
    project_to_plane_2d,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PaneConfig:
    min_pixels: int = bounded(16, ge=1)
    """Components with fewer pixels are skipped."""
    perimeter_samples: int = bounded(256, ge=3)
    """At most this many perimeter pixels (evenly spaced) go into the plane fit and hull."""
    min_points: int = bounded(3, ge=3)
    """Fewest perimeter pixels with valid depth needed for a fit."""
    max_rms_rel: float = bounded(0.02, gt=0.0)
    """A component is not planar when the fit's RMS residual exceeds this times the points' mean range."""
    eight_connected: bool = True
    """Connect diagonal neighbours (8-connectivity) rather than only edge neighbours (4-connectivity)."""


@dataclass(frozen=True)
class Pane:
    """One planar pane.

    Attributes:
        plane: the fitted plane (normal towards the camera origin).
        vertices_m: (K, 3) convex polygon corners on the plane, CCW seen from the normal's side.
        faces: (K - 2, 3) fan triangles into ``vertices_m`` (normals along ``plane.normal``).
        label: the connected-component label (1-based) in the mask.
        n_points: perimeter points used in the fit.
    """

    plane: Plane
    vertices_m: np.ndarray
    faces: np.ndarray
    label: int
    n_points: int


@dataclass(frozen=True)
class PaneResult:
    """Panes found in a mask and the components that were skipped.

    Attributes:
        panes: the accepted panes.
        labels: (H, W) int32 connected-component labels of the mask (0 = outside).
        rejected: (label, reason) for every skipped component.
    """

    panes: tuple[Pane, ...]
    labels: np.ndarray
    rejected: tuple[tuple[int, str], ...]


def pane_from_points(points: np.ndarray, toward: np.ndarray | None = None) -> tuple[Plane, np.ndarray, np.ndarray]:
    """Plane fit, in-plane convex hull and fan triangulation of 3D points ``(N, 3)``.

    Returns:
        ``(plane, vertices (K, 3), faces (K - 2, 3))``.

    Raises:
        DegenerateGeometryError: fewer than 3 points, coincident or collinear points (no plane or no hull).
        InputError: for arrays of the wrong shape.
    """
    plane = fit_plane(points, toward)
    xy = project_to_plane_2d(points, plane)
    hull = convex_hull_2d(xy)
    return plane, lift_from_plane_2d(xy[hull], plane), fan_triangulate(len(hull))


def perimeter_pixels(component: np.ndarray) -> np.ndarray:
    """(K, 2) ``(row, col)`` of the pixels of a boolean mask that touch its outside (image border included)."""
    inner = ndimage.binary_erosion(component, structure=np.ones((3, 3), bool), border_value=0)
    return np.argwhere(component & ~inner)


def extract_panes(mask: np.ndarray, points_cam: np.ndarray, valid: np.ndarray, cfg: PaneConfig) -> PaneResult:
    """Algorithm 1 on every connected component of ``mask`` (see the module docstring).

    Args:
        mask: (H, W) bool pane mask.
        points_cam: (H, W, 3) camera-frame points (:func:`cadalign.geometry.depth_to_points`), metres.
        valid: (H, W) bool: the pixel has a valid depth.
        cfg: thresholds.
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2 or points_cam.shape != mask.shape + (3,) or valid.shape != mask.shape:
        raise InputError(f"pane mask {mask.shape}, points {points_cam.shape} and valid {valid.shape} must share "
                         "(H, W)")
    structure = np.ones((3, 3), bool) if cfg.eight_connected else None
    labels, n = ndimage.label(mask, structure=structure)
    panes, rejected = [], []
    for lab in range(1, n + 1):
        comp = labels == lab
        reason = _component_pane(comp, lab, points_cam, valid, cfg, panes)
        if reason is not None:
            rejected.append((lab, reason))
            log.debug("pane component %d skipped: %s", lab, reason)
    return PaneResult(tuple(panes), labels.astype(np.int32), tuple(rejected))


def _component_pane(comp: np.ndarray, lab: int, points_cam: np.ndarray, valid: np.ndarray, cfg: PaneConfig,
                    out: list[Pane]) -> str | None:
    """Append the pane of one component to ``out``; the reason it was skipped otherwise."""
    size = int(comp.sum())
    if size < cfg.min_pixels:
        return f"{size} pixels < min_pixels {cfg.min_pixels}"
    rim = perimeter_pixels(comp)
    rim = rim[valid[rim[:, 0], rim[:, 1]]]
    if len(rim) > cfg.perimeter_samples:
        rim = rim[np.linspace(0, len(rim) - 1, cfg.perimeter_samples).round().astype(np.int64)]
    if len(rim) < cfg.min_points:
        return f"{len(rim)} perimeter pixels with valid depth < min_points {cfg.min_points}"
    pts = points_cam[rim[:, 0], rim[:, 1]]
    try:
        plane, verts, faces = pane_from_points(pts)
    except DegenerateGeometryError as exc:
        return f"degenerate: {exc}"
    scale = float(np.mean(np.linalg.norm(pts, axis=1)))
    if plane.rms > cfg.max_rms_rel * scale:
        return f"not planar: RMS {plane.rms:.3g} m > {cfg.max_rms_rel} x mean range {scale:.3g} m"
    out.append(Pane(plane, verts, faces, lab, len(pts)))
    return None

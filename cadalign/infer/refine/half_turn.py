"""Half-turn check: is a refined pose, or the pose turned half a turn about the model's z axis, the better view?

A part that is nearly but not exactly invariant to a half turn about z (the default scene's ball valve: a
symmetric body with its lever off-centre, 0.2 m between the two lever positions) is predicted by a network in
either orientation, and a depth fit of the observed points to the model (data -> model, what ICP and
:func:`cadalign.infer.refine.depth_icp.depth_fit` measure) barely prefers the right one: the few lever pixels are all
that differ, and a model lever where nothing is seen costs nothing. The check scores both poses *from the
model's side* as well: it renders the model's depth and counts the pixels where

- the camera sees *through* the model: the observed depth is behind the rendered surface by more than
  ``tol`` (free space the model claims to fill), and
- the predicted mask holds observed depth near the object but the model has no surface there (an unexplained
  part of the object).

Occluders (observed depth in front of the model) and pixels without depth do not count. Without a depth map
the disagreement is that of the silhouettes: the pixels in exactly one of the model's rendered silhouette and
the predicted mask. Only disagreement at least ``band_px`` away from the other side's outline counts (a
see-through pixel that far from the mask, an unexplained mask pixel that far from the rendered silhouette), so a
pose a few degrees off (its whole outline a pixel off; ICP on a few hundred noisy depth points at 12 m leaves
that) does not outscore the wrong half turn, whose lever (or other asymmetric part) sticks out several pixels.
Models that are invariant to some turn about z (their symmetry says so) are left alone.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import distance_transform_edt

from cadalign.cad.symmetry import Symmetry
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.model_geom import ModelGeometry, project_points, render_depth
from cadalign.infer.refine.hypotheses import yaw_period_rad
from cadalign.types import Rigid3


def needs_half_turn_check(symmetry: Symmetry | None) -> bool:
    """True when no turn about the model's z axis leaves it unchanged (:func:`yaw_period_rad` is a full turn)."""
    return yaw_period_rad(symmetry) > 2 * math.pi - 1e-6


def half_turned(T: Rigid3) -> Rigid3:
    """``T`` turned half a turn about the model's own z axis (through its origin)."""
    return Rigid3(T.R @ axis_angle_to_matrix(np.array([0.0, 0.0, math.pi])), T.t)


def view_window(geom: ModelGeometry, poses: list[Rigid3], K: np.ndarray, mask: np.ndarray) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) covering the mask and every pose's projected surface samples (+2 px), clipped to the image."""
    h, w = mask.shape
    pts = [np.argwhere(mask)[:, ::-1].astype(float) + 0.5] if mask.any() else []
    for T in poses:
        Xc = T.apply(geom.samples)
        Xc = Xc[Xc[:, 2] > 1e-3]
        if len(Xc):
            pts.append(project_points(K, Xc))
    if not pts:
        return 0, 0, 0, 0
    uv = np.concatenate(pts)
    lo = np.clip(np.floor(uv.min(0)).astype(int) - 2, 0, [w, h])
    hi = np.clip(np.ceil(uv.max(0)).astype(int) + 2, 0, [w, h])
    return int(lo[0]), int(lo[1]), int(hi[0]), int(hi[1])


def _far_from(region: np.ndarray, band_px: float) -> np.ndarray:
    """Pixels at least ``band_px`` from every pixel of ``region`` (all of them when it is empty)."""
    if band_px <= 0 or not region.any():
        return np.ones(region.shape, bool)
    return distance_transform_edt(~region) >= band_px


def view_disagreement(geom: ModelGeometry, T: Rigid3, K: np.ndarray, mask: np.ndarray,
                      depth_m: np.ndarray | None, tol_m: float, window: tuple[int, int, int, int],
                      band_px: float = 0.0, near: tuple[float, float] | None = None) -> int:
    """Pixels of ``window`` = (x0, y0, x1, y1) where the model at ``T`` disagrees with the observation.

    With ``depth_m`` (H, W) metres: see-through pixels plus unexplained mask pixels (module docstring), with
    depth tolerance ``tol_m``; without: the silhouette XOR the mask. Disagreement within ``band_px`` of the other
    side's outline is not counted. A mask pixel is of the object (and unexplained when the model misses it) when
    its depth is within the model's diameter of the model's origin; ``near`` = (depth, band) m fixes that test
    instead, for comparing poses far apart in depth (different models of a class, one of them fitted a few metres
    off would otherwise leave no mask pixel "near" it).
    """
    return sum(view_disagreement_parts(geom, T, K, mask, depth_m, tol_m, window, band_px, near))


def view_disagreement_parts(geom: ModelGeometry, T: Rigid3, K: np.ndarray, mask: np.ndarray,
                            depth_m: np.ndarray | None, tol_m: float, window: tuple[int, int, int, int],
                            band_px: float = 0.0, near: tuple[float, float] | None = None) -> tuple[int, int]:
    """:func:`view_disagreement` as (pixels seen through the model, mask pixels it leaves unexplained); without
    depth (silhouette pixels off the mask, mask pixels off the silhouette)."""
    x0, y0, x1, y1 = window
    if x1 <= x0 or y1 <= y0:
        return 0, 0
    z_model = render_depth(geom, T, np.asarray(K, float), (y1 - y0, x1 - x0), (x0, y0))
    hit = np.isfinite(z_model)
    m = np.asarray(mask, bool)[y0:y1, x0:x1]
    off_mask, off_model = _far_from(m, band_px), _far_from(hit, band_px)
    if depth_m is None:
        return int(np.count_nonzero(hit & ~m & off_mask)), int(np.count_nonzero(m & ~hit & off_model))
    obs = np.asarray(depth_m, float)[y0:y1, x0:x1]
    valid = np.isfinite(obs) & (obs > 0)
    see_through = hit & valid & (obs > np.where(hit, z_model, 0.0) + tol_m) & off_mask
    z_ref, band = (float(T.t[2]), geom.diameter_m) if near is None else near
    unexplained = ~hit & m & valid & (np.abs(obs - z_ref) < band) & off_model
    return int(np.count_nonzero(see_through)), int(np.count_nonzero(unexplained))


def pick_half_turn(geom: ModelGeometry, T: Rigid3, T_turned: Rigid3, K: np.ndarray, mask: np.ndarray,
                   depth_m: np.ndarray | None, tol_m: float, min_px: int, band_px: float = 0.0
                   ) -> tuple[Rigid3, tuple[int, int]]:
    """``T_turned`` when it disagrees with the view in at least ``min_px`` fewer pixels than ``T``, else ``T``.

    Both are scored on the same window (:func:`view_disagreement`); returns the pose and the two counts.
    """
    win = view_window(geom, [T, T_turned], np.asarray(K, float), np.asarray(mask, bool))
    a = view_disagreement(geom, T, K, mask, depth_m, tol_m, win, band_px)
    b = view_disagreement(geom, T_turned, K, mask, depth_m, tol_m, win, band_px)
    return (T_turned if b + min_px <= a else T), (a, b)

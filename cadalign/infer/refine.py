"""Refinement of a 6-DoF pose against the CAD model: silhouette/contour alignment and depth ICP.

(a) :func:`refine_silhouette`: damped Gauss-Newton (Levenberg-Marquardt with step acceptance) on the signed
distance transform of the predicted mask, sampled at the projections of the model's outline points: points
on the occluding contour (edges between a front- and a back-facing face) that also lie on the outline of
the model's own rendered silhouette. Each residual is the signed distance (px) of a projected outline point
to the mask boundary, so the outline is pulled onto the zero level set from both sides (a shrunken or
grown silhouette is penalised, unlike a one-sided chamfer); residuals are Huber-weighted and truncated.

(b) :func:`refine_depth_icp`: point-to-plane ICP of surface samples of the CAD to the back-projected depth
inside the (eroded) mask, Huber-weighted, correspondences found in the model frame (one k-d tree per model).

Both update the pose by ``(omega, v)`` (:func:`apply_twist`): a turn about the object's origin in camera axes
and a shift. A point moves as ``X' = X + omega x (X - t) + v``; its projection's Jacobian is
``du/dX [-[X - t]_x, I]``. A Gaussian prior on the deviation from the detector's pose fixes directions the
data do not observe.

The silhouette alignment lives in :mod:`cadalign.infer.contour_fit`, the depth ICP in
:mod:`cadalign.infer.depth_icp` and their shared update/solve in :mod:`cadalign.infer.refine_math`; this module
holds the config, the presets and :func:`refine`, and re-exports the public functions of the three.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from cadalign.cad.symmetry import Symmetry
from cadalign.geometry.rotations import axis_angle_to_matrix, geodesic_angle
from cadalign.infer.config import REFINE_PRESETS as PRESETS
from cadalign.infer.config import RefineConfig
from cadalign.infer.contour_fit import SignedDistance, refine_silhouette, silhouette_iou
from cadalign.infer.depth_icp import (
    ICP_DAMPING,
    depth_along_ray,
    depth_fit,
    icp_points,
    masked_depth_points,
    refine_depth_icp,
)
from cadalign.infer.half_turn import half_turned, needs_half_turn_check, pick_half_turn
from cadalign.infer.hypotheses import yaw_hypotheses_rad
from cadalign.infer.model_geom import ModelGeometry
from cadalign.infer.refine_math import apply_twist
from cadalign.types import Rigid3

__all__ = [
    "ICP_DAMPING", "PRESETS", "RefineConfig", "RefineResult", "SignedDistance", "apply_twist", "depth_along_ray",
    "depth_fit", "icp_points", "masked_depth_points", "pick_fit", "refine", "refine_depth_icp", "refine_silhouette",
    "silhouette_iou",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RefineResult:
    """The refined pose, the iterations run per stage, the cost after each iteration and the time taken."""

    T_cam_from_obj: Rigid3
    iterations: dict[str, int] = field(default_factory=dict)
    costs: dict[str, list[float]] = field(default_factory=dict)
    seconds: float = 0.0


def refine(geom: ModelGeometry, T_init: Rigid3, K: np.ndarray, mask: np.ndarray, cfg: RefineConfig,
           depth_m: np.ndarray | None = None, symmetry: Symmetry | None = None) -> RefineResult:
    """Run the configured refinements in order (silhouette, then depth ICP when ``depth_m`` is given).

    ``symmetry`` (the model's) spreads the yaw restarts over the turn it leaves distinct (``cfg.yaw_hypotheses``).
    """
    t0 = time.perf_counter()
    T, iters, costs = T_init, {}, {}
    if cfg.method in ("silhouette", "both"):
        T, iters["silhouette"], costs["silhouette"] = refine_silhouette(geom, T, K, mask, cfg)
    if cfg.method in ("depth", "both") and depth_m is not None:
        T, iters["depth"], costs["depth"] = _icp_yaw_hypotheses(geom, T, K, depth_m, mask, cfg, symmetry)
    fitted = any(iters.values())  # comparing unfitted poses scores their misalignment, not their orientation
    if cfg.half_turn_check and fitted and needs_half_turn_check(symmetry):
        T, iters["half_turn"] = _half_turn(geom, T, K, np.asarray(mask, bool), cfg, depth_m)
    return RefineResult(T, iters, costs, time.perf_counter() - t0)


def _half_turn(geom: ModelGeometry, T: Rigid3, K: np.ndarray, mask: np.ndarray, cfg: RefineConfig,
               depth_m: np.ndarray | None) -> tuple[Rigid3, int]:
    """``T`` or its refined half turn, whichever agrees better with the view; 1 when the turn was taken.

    The turned pose must be fitted as ``T`` was (some refinement iterations run), else ``T`` stays."""
    T_alt, n = half_turned(T), 0
    if cfg.method in ("silhouette", "both"):
        T_alt, k, _ = refine_silhouette(geom, T_alt, K, mask, cfg)
        n += k
    if cfg.method in ("depth", "both") and depth_m is not None:
        T_alt, k, _ = refine_depth_icp(geom, T_alt, K, depth_m, mask, cfg)
        n += k
    if n == 0:
        return T, 0
    best, _ = pick_half_turn(geom, T, T_alt, K, mask, depth_m, cfg.half_turn_tol * geom.diameter_m,
                             cfg.half_turn_min_px, cfg.half_turn_band_px)
    return best, int(best is T_alt)


def _icp_yaw_hypotheses(geom: ModelGeometry, T0: Rigid3, K: np.ndarray, depth_m: np.ndarray, mask: np.ndarray,
                        cfg: RefineConfig, symmetry: Symmetry | None = None) -> tuple[Rigid3, int, list[float]]:
    best = refine_depth_icp(geom, T0, K, depth_m, mask, cfg)
    if cfg.yaw_hypotheses <= 1 or best[1] == 0:
        return best
    Q = icp_points(depth_m, mask, K, cfg)
    scored = [(depth_fit(geom, best[0], Q), best)]
    for angle in yaw_hypotheses_rad(cfg.yaw_hypotheses, symmetry)[1:]:
        yaw = axis_angle_to_matrix(np.array([0.0, 0.0, angle]))
        cand = refine_depth_icp(geom, Rigid3(T0.R @ yaw, T0.t), K, depth_m, mask, cfg)
        scored.append((depth_fit(geom, cand[0], Q), cand))
    return scored[pick_fit([f for f, _ in scored], [c[0] for _, c in scored], T0, cfg.tie_m)][1]


def pick_fit(fits: Sequence[float], poses: Sequence[Rigid3], T_ref: Rigid3, tie_m: float) -> int:
    """Index of the best (smallest) fit, or among the fits within ``tie_m`` of it the one whose pose turns least
    from ``T_ref`` (``poses[i]`` goes with ``fits[i]``; the first wins equal fits)."""
    best = int(np.argmin(fits))
    near = [i for i, f in enumerate(fits) if f <= fits[best] + tie_m]
    if len(near) == 1 or tie_m <= 0:
        return best
    return min(near, key=lambda i: float(geodesic_angle(poses[i].R, T_ref.R)))

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
from typing import Literal

import numpy as np

from cadalign.cad.symmetry import Symmetry
from cadalign.config import bounded
from cadalign.geometry.rotations import axis_angle_to_matrix, geodesic_angle
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
class RefineConfig:
    method: Literal["none", "silhouette", "depth", "both"] = "both"
    """Which refinements run: ``both`` = silhouette, then depth ICP when a depth map is given."""
    silhouette_iters: int = bounded(15, ge=0)
    """Gauss-Newton iterations of the contour alignment."""
    depth_iters: int = bounded(10, ge=0)
    """Point-to-plane ICP iterations."""
    min_mask_px: int = bounded(400, ge=1)
    """Silhouette refinement is skipped for smaller masks: their outline says too little about the pose."""
    min_depth_points: int = bounded(10, ge=6)
    """ICP is skipped with fewer valid depth points inside the mask. Was 50, which left most small detections
    unrefined (43 of 45 hot stab detections on the two-pass capture). Chosen on the two-pass capture's val frames
    (refined valve t 0.177 -> 0.051 m mean; 6 is the same as 10) and confirmed on its test frames (0.087 ->
    0.029 m) and on the default orbit's held-out frames (valves unchanged; hot stab t 0.558 -> 0.341 m)."""
    max_contour_points: int = bounded(400, ge=10)
    """Model contour points per iteration (evenly thinned)."""
    huber_px: float = bounded(2.0, gt=0)
    """Huber threshold of the contour residuals, pixels."""
    trunc_px: float = bounded(25.0, gt=0)
    """Contour residuals longer than this (pixels) are ignored (other objects' edges, occluders)."""
    own_edge_px: float = bounded(0.8, gt=0)
    """A contour point is on the outline when within this (px) of its own rendered silhouette's boundary."""
    max_depth_points: int = bounded(1500, ge=10)
    """Back-projected depth points used by ICP."""
    icp_max_corr: float = bounded(0.1, gt=0)
    """Largest ICP correspondence distance as a fraction of the model diameter."""
    icp_huber_m: float = bounded(0.005, gt=0)
    """Huber threshold of the point-to-plane residuals, metres."""
    prior_t_m: float = bounded(0.05, gt=0)
    """Standard deviation of the prior on the detector's translation (m), for unobserved directions."""
    prior_r_deg: float = bounded(5.0, gt=0)
    """Standard deviation of the prior on the detector's rotation (deg)."""
    icp_max_corr_start: float = bounded(0.5, gt=0)
    """ICP's wide gate (fraction of the diameter), while under half the points pair within ``icp_max_corr``."""
    damping: float = bounded(1e-2, ge=0)
    """Silhouette: Levenberg-Marquardt damping, relative to the mean diagonal of the normal matrix."""
    min_step: float = bounded(1e-6, ge=0)
    """Stop when the update's rotation (rad) and translation / diameter both fall below this."""
    depth_init: bool = True
    """Before ICP, slide the pose along its viewing ray by the median offset between the masked depth and the
    model's visible surface, when that is more than ICP's narrow gate (``icp_max_corr`` diameters). A network's
    translation error is mostly depth (the box size at a few pixels is off by 10 %, i.e. ~1 m at 10 m), far
    beyond ICP's gate and its prior on the detector's pose."""
    yaw_hypotheses: int = bounded(1, ge=1)
    """Depth ICP restarts from the pose turned about the model's z axis by multiples of P / n, keeping the
    best depth fit (1 = the detector's pose only), where P is the yaw range the model's symmetry leaves distinct
    (360 deg, 180 deg for a half-turn symmetry about z; :mod:`cadalign.infer.hypotheses`). Upright parts
    (valves on a frame) are mostly wrong in yaw by more than ICP's basin when a network is unsure."""
    half_turn_check: bool = False
    """After refinement, also refine the pose turned half a turn about the model's z axis and keep whichever
    disagrees with the view in fewer pixels (rendered model depth against the observed depth: see-through and
    unexplained mask pixels; silhouette XOR mask without depth; :mod:`cadalign.infer.half_turn`). Only for models
    that no turn about z leaves unchanged (their symmetry), and only when both poses were fitted (some refinement
    ran: unfitted poses differ mostly by misalignment). A nearly half-turn symmetric part (a ball valve with an
    off-centre lever) comes out of a network in either orientation, and the depth fit of the data to the model
    barely tells them apart. Measured on the default scene's 16 held-out frames with ``yaw_hypotheses = 4``: oracle
    detections (3 cm / 3 deg noise) refined valve R mean 7.9 -> 0.6 deg (ball valve 43.5 -> 2.3 deg, 13/13 on the
    right side); the 3300-step zoom network (pose_fast_zoom_improved.toml) 13.8 -> 15.3 deg: its ball-valve
    rotations start 40-180 deg off and 5 of 12 are identified as another valve, beyond what a half turn fixes.
    Off by default for that reason (/work/runs_shared/pose_c/RESULTS.md)."""
    half_turn_tol: float = bounded(0.05, gt=0)
    """Depth tolerance of the half-turn check, in model diameters (observed depth this far behind the rendered
    surface is seen through it)."""
    half_turn_min_px: int = bounded(3, ge=0)
    """The half-turned pose must disagree with the view in at least this many fewer pixels to be taken."""
    half_turn_band_px: float = bounded(1.5, ge=0)
    """Disagreement within this many pixels of the other side's outline is not counted (a pose a few degrees off
    is a pixel off all round; the lever of the default scene's wrong-way ball valve sticks out ~5 px at 12 m)."""
    tie_m: float = bounded(0.0, ge=0)
    """Fits within this (m) of the best depth fit are ties, and the tie closest in rotation to the start pose wins
    (among the yaw restarts here, and among the candidate models in the pipeline's identification). 0: the best
    fit wins outright. A part seen from far or partly hidden fits several poses equally (a hot stab hidden to 40 %
    fits end-for-end within 0.5 mm), and the start (the network's or a track's pose) is then the better guide.
    ``accurate`` uses 3 mm, chosen on the default orbit's val frames with the 6600-step network (fused valve R mean
    12.5 / 3.5 / 1.2 deg for 0 / 1 / 3 mm, hot stab 82 / 82 / 51 deg; its test frames: 13.2 / 0.2 / 0.9 and
    121 / 120 / 45). It trusts the start: the 3300-step network, whose rotations are worse (40 vs 29 deg mean
    for valves), goes from 3.7 to 5.6 deg on val with 3 mm."""
    seed: int = 0
    """Seed of the point subsampling."""


PRESETS: dict[str, RefineConfig] = {
    "none": RefineConfig(method="none"),
    "fast": RefineConfig(silhouette_iters=5, depth_iters=5, max_contour_points=200, max_depth_points=600),
    "balanced": RefineConfig(),
    "accurate": RefineConfig(silhouette_iters=30, depth_iters=20, max_contour_points=800, max_depth_points=4000,
                             yaw_hypotheses=4, tie_m=0.003),
}


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

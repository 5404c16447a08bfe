"""The per-part refinement run in order: :func:`refine` (silhouette, then depth ICP with yaw restarts, then the
half-turn check), its :class:`RefineResult`, and :func:`pick_fit`, the choice among fits that tie.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from cadalign.cad.symmetry import Symmetry
from cadalign.geometry.rotations import axis_angle_to_matrix, geodesic_angle
from cadalign.infer.config import RefineConfig
from cadalign.infer.model_geom import ModelGeometry
from cadalign.infer.refine.contour_fit import refine_silhouette
from cadalign.infer.refine.depth_icp import depth_fit, icp_points, refine_depth_icp
from cadalign.infer.refine.half_turn import half_turned, needs_half_turn_check, pick_half_turn
from cadalign.infer.refine.hypotheses import yaw_hypotheses_rad
from cadalign.types import Rigid3

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

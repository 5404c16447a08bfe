"""The config of pose refinement (:func:`cadalign.infer.refine.refine`), apart from the solvers it configures so
that :mod:`~cadalign.infer.contour_fit`, :mod:`~cadalign.infer.depth_icp` and :mod:`~cadalign.infer.refine_math`
read it without importing :mod:`cadalign.infer.refine`, which imports them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from cadalign.config import bounded


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

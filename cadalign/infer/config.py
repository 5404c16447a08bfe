"""The configs of inference, in one place: refinement (:class:`RefineConfig`, :data:`REFINE_PRESETS`), the
detector's zoomed windows (:class:`TileConfig`), temporal fusion (:class:`TemporalConfig`), the multi-frame refit
(:class:`RefitConfig`) and track completion (:class:`CompleteConfig`), and the whole (:class:`InferConfig`,
:data:`PRESETS`). Configs only: the solvers import them, this module imports no solver. Each field's docstring gives
its meaning and unit; the measurements behind the defaults are in ``docs/tuning/infer_config.md``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
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
    """ICP is skipped with fewer valid depth points inside the mask (50 left most small detections unrefined).
    Measurements: docs/tuning/infer_config.md#refineconfigmin_depth_points."""
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
    """Before ICP, slide the pose along its viewing ray by the median offset between the masked depth and the model's
    visible surface, when that is more than ICP's narrow gate (``icp_max_corr`` diameters). Measurements:
    docs/tuning/infer_config.md#refineconfigdepth_init."""
    yaw_hypotheses: int = bounded(1, ge=1)
    """Depth ICP restarts from the pose turned about the model's z axis by multiples of P / n (P: the yaw range its
    symmetry leaves distinct; :mod:`cadalign.infer.refine.hypotheses`), keeping the best depth fit; 1 = the detector's
    pose only. Measurements: docs/tuning/infer_config.md#refineconfigyaw_hypotheses."""
    half_turn_check: bool = False
    """After refinement, also refine the pose turned half a turn about the model's z axis and keep whichever disagrees
    with the view in fewer pixels (:mod:`cadalign.infer.refine.half_turn`). Measurements:
    docs/tuning/infer_config.md#refineconfighalf_turn_check."""
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
    (among the yaw restarts here, and among the candidate models in the pipeline's identification). 0: the best fit wins
    outright. Measurements: docs/tuning/infer_config.md#refineconfigtie_m."""
    seed: int = 0
    """Seed of the point subsampling."""


REFINE_PRESETS: dict[str, RefineConfig] = {
    "none": RefineConfig(method="none"),
    "fast": RefineConfig(silhouette_iters=5, depth_iters=5, max_contour_points=200, max_depth_points=600),
    "balanced": RefineConfig(),
    "accurate": RefineConfig(silhouette_iters=30, depth_iters=20, max_contour_points=800, max_depth_points=4000,
                             yaw_hypotheses=4, tie_m=0.003),
}


@dataclass(frozen=True)
class TileConfig:
    """Zoomed windows of each frame (test-time): parts a few pixels across are seen as the network sees nearer ones.

    With ``zoom`` > 1 the network also runs on overlapping windows ``1 / zoom`` of the frame, each upsampled to
    its input (``K`` moves with the window, so poses stay in the frame's camera); a window's detection that
    touches an inner window edge is cut and left to the whole-frame pass or a neighbour; the union is
    non-maximum suppressed per class (:class:`TorchDetector`'s ``nms_iou``). Each window costs a whole detector
    pass."""

    zoom: float = bounded(1.0, ge=1)
    """Window size as a fraction ``1 / zoom`` of the frame (1 = off: the whole frame only)."""
    overlap: float = bounded(0.25, ge=0, lt=1)
    """Least fraction of a window shared with its neighbour (parts up to ``overlap / zoom`` of the frame are
    whole in some window)."""
    border_px: float = bounded(2.0, ge=0)
    """A window's detection within this many frame pixels of an inner window edge counts as cut."""
    score_thresh: float = bounded(0.5, ge=0, le=1)
    """A window's detections scoring below this are dropped (the whole-frame pass keeps the detector's threshold):
    the windows add recall and, at the same threshold, false positives."""
    max_box_px: float = bounded(0.0, ge=0)
    """A window's detection whose box is longer than this (frame pixels) on either side is dropped (0 = keep all): the
    windows then add only parts too small for the whole frame, and larger parts come from the whole frame alone.
    Measurements: docs/tuning/infer_config.md#tileconfigmax_box_px."""


@dataclass(frozen=True)
class TemporalConfig:
    mode: Literal["auto", "world", "ego", "filter", "none"] = "auto"
    """``auto``: the world robust mean where the frame's camera pose is known, else ``ego`` (camera poses from the
    static parts). Measurements: docs/tuning/infer_config.md#temporalconfigmode."""
    window: int = bounded(30, ge=1)
    """Observations per track in the world robust mean."""
    huber_t_m: float = bounded(0.05, gt=0)
    """Huber threshold of translation residuals (m) in the robust mean."""
    huber_r_deg: float = bounded(5.0, gt=0)
    """Huber threshold of rotation residuals (deg) in the robust mean."""
    alpha: float = bounded(0.5, gt=0, le=1)
    """Filter gain on the pose innovation (1 = trust each measurement)."""
    beta: float = bounded(0.167, ge=0, le=1)
    """Filter gain on the velocity (``alpha^2 / (2 - alpha)``: the critically damped pair)."""
    gate_m: float = bounded(0.3, gt=0)
    """Association / outlier gate on translation (m); parts smaller than twice it use half their diameter."""
    gate_deg: float = bounded(30.0, gt=0)
    """Outlier gate of the filter on rotation (deg) after symmetry canonicalisation."""
    max_missed: int = bounded(5, ge=0)
    """A filter track whose observations are rejected this many frames in a row restarts from the next one."""


@dataclass(frozen=True)
class RefitConfig:
    enabled: bool = True
    """Refit each completed track's world pose to all its frames' depth before completion (see module doc)."""
    points_per_frame: int = bounded(300, ge=6)
    """Masked depth points kept per detection (world frame)."""
    max_points: int = bounded(2000, ge=6)
    """Points of the final ICP (a random subset of the union)."""
    coarse_points: int = bounded(300, ge=6)
    """Points of the first, short ICP from every start."""
    coarse_iters: int = bounded(20, ge=1)
    """ICP iterations from every start (30 helped one network's hot stab and hurt two others). Measurements:
    docs/tuning/infer_config.md#refitconfigcoarse_iters."""
    keep: int = bounded(4, ge=1)
    """Starts (besides the fused pose) taken on to the final ICP."""
    iters: int = bounded(30, ge=1)
    """Final ICP iterations."""
    anchors: int = bounded(12, ge=1)
    """Model points put on the points' centroid per start rotation (its centroid, then farthest-point samples)."""
    hops: tuple[float, ...] = (0.1, 0.2)
    """Translation hops: the fused pose and the best ``keep`` coarse fits are moved along each principal axis of the
    model by these fractions of its diameter, both ways, and fitted again (coarse, 6 more starts per fit and fraction);
    the best ``keep`` of them join the final ICP too. Measurements: docs/tuning/infer_config.md#refitconfighops."""
    tie_rel: float = bounded(0.02, ge=0)
    """Fits within this fraction of the best are ties (the one nearest the fused pose wins)."""
    huber_m: float = bounded(0.005, gt=0)
    """Huber threshold of the point-to-plane residuals, metres."""
    min_points: int = bounded(30, ge=6)
    """A track with fewer points in all keeps its fused pose."""
    ego: bool = False
    """Refit tracks in the worlds of camera poses registered on the parts (temporal mode ``ego``) too. Measurements:
    docs/tuning/infer_config.md#refitconfigego."""
    dup_tol: float = bounded(0.02, gt=0)
    """A point is explained by a pose when within this fraction of the diameter of the model (the duplicate test)."""
    dup_share: float = bounded(0.8, ge=0, le=1)
    """Two refitted tracks of a class are one part when one's pose explains at least this share of what the other's own
    pose explains of the other's points; the one closer to both tracks' points is kept (:func:`duplicates`). 0 = off.
    Measurements: docs/tuning/infer_config.md#refitconfigdup_share."""
    choose_model: Literal["off", "depth", "view"] = "view"
    """Refit every CAD model of the track's class, not only the track's own, and keep the one that fits best
    (:func:`pick_model`): a track's model is chosen on its first, smallest views. Measurements:
    docs/tuning/infer_config.md#refitconfigchoose_model."""
    model_margin: float = bounded(0.1, ge=0)
    """Another model replaces the track's own only when its score is better by more than this fraction."""
    mask_weight: float = bounded(0.25, ge=0)
    """Weight, in :func:`view_score`, of a mask pixel the model leaves unexplained against a pixel seen through the
    model. Measurements: docs/tuning/infer_config.md#refitconfigmask_weight."""
    model_min_px: float = bounded(2.0, ge=0)
    """... and (``choose_model = "view"``) by more than this many pixels per view: the 87 mm valve's 14-20 px masks
    disagree with its own model in 3 pixels and with the 145 mm valve's in none."""
    screen: bool = True
    """With ``choose_model``, the other models of the class are first fitted by a cheaper search (at most 6 anchors, 150
    coarse points, 10 coarse iterations, 2 kept: :meth:`screening`); a model that wins on that fit is fitted again by
    the full search before it replaces the track's own. Measurements: docs/tuning/infer_config.md#refitconfigscreen."""
    view_turns_deg: tuple[float, ...] = (16.0, 8.0, 4.0)
    """With ``choose_model = "view"``, turns (deg, coarse to fine) of the chosen fit about the model's axes, taken while
    a turn lowers :func:`view_score` and keeps the points' fit within ``tie_rel`` (:func:`turn_by_view`). Measurements:
    docs/tuning/infer_config.md#refitconfigview_turns_deg."""
    turn_icp_iters: tuple[int, ...] = (0, 10)
    """The turns of ``view_turns_deg`` are searched once per entry, each turn followed by that many ICP iterations (so
    that the part's position follows the turn; 0: the turn alone); the result with the lowest :func:`view_score` is kept
    (ties: the first). Measurements: docs/tuning/infer_config.md#refitconfigturn_icp_iters."""
    turn_min_px: float = bounded(0.5, ge=0)
    """The turns of ``view_turns_deg`` are kept only when they lower :func:`view_score` by more than this many
    pixels per view in all: the UUV hot stab's 7 views fell 11.75 -> 5.75 (16.3 -> 1.0 deg off); the 87 mm valve's 9
    views (15-33 px masks; seed 2, 4200 steps) 7.0 -> 5.75, turning it 0.6 -> 5.9 deg off."""
    view_pick_rel: float = bounded(1.0, ge=0)
    """With views (``choose_model = "view"``), the final fits within this fraction of the best points' fit are compared
    by :func:`view_score` too: those within ``turn_min_px`` per view of the lowest are ties (then the ``tie_rel`` rule
    among them). Measurements: docs/tuning/infer_config.md#refitconfigview_pick_rel."""
    view_pick_max_fit: float = bounded(0.04, gt=0)
    """...and only when the best points' fit is within this fraction of the model's diameter: the views choose among
    fits that explain the points, not a new place for a track that no fit explains. Measurements:
    docs/tuning/infer_config.md#refitconfigview_pick_max_fit."""
    view_pad: float = bounded(1.0, ge=0)
    """A detection's view (``choose_model = "view"``) is its mask's box grown by this times its longer side."""
    max_views: int = bounded(40, ge=1)
    """Views kept per track at most (a uniform sample of its detections, reservoir-drawn): a view is a depth crop of
    up to ~1 MB for a part near the camera, and a long video would otherwise keep all of them."""
    seed: int = 0
    """Seed of the point subsampling."""

    def screening(self) -> RefitConfig:
        """The cheaper search of ``screen``."""
        return dataclasses.replace(self, anchors=min(self.anchors, 6), coarse_points=min(self.coarse_points, 150),
                                   coarse_iters=min(self.coarse_iters, 10), keep=min(self.keep, 2))


@dataclass(frozen=True)
class CompleteConfig:
    enabled: bool = False
    """Run the completion pass after the video (needs depth and the frames' camera poses, given or registered on
    the parts; see module doc)."""
    min_obs: int = bounded(3, ge=1)
    """Detections a track needs to be completed into other frames (and, with ``drop_short``, to be reported)."""
    drop_short: bool = True
    """Drop the detections of tracks with fewer than ``min_obs`` detections."""
    consistency_iou: float = bounded(0.3, ge=0, le=1)
    """Median box IoU of a track's projected world pose and its own detections needed to complete it."""
    min_visible: float = bounded(0.1, gt=0, le=1)
    """Fraction of the projected silhouette that the depth map must show in sight for the part to be reported (0.1:
    BOP's rule for which parts count as targets).
    Measurements: docs/tuning/infer_config.md#completeconfigmin_visible."""
    depth_tol_m: float = bounded(0.05, ge=0)
    """A model pixel is in sight when its depth is at most the observed depth plus this (metres)..."""
    depth_tol_rel: float = bounded(0.0, ge=0)
    """...or plus this fraction of the model's depth there, whichever is larger (for predicted depth)."""
    min_detected: float = bounded(0.0, ge=0, le=1)
    """Fraction of the frames showing a track's part in sight (by its projection) in which it must have been detected to
    be completed: a false positive that recurs in a few frames at one place is otherwise reported in every frame that
    sees that place. Measurements: docs/tuning/infer_config.md#completeconfigmin_detected."""
    drop_untrusted: bool = False
    """Drop the detections of tracks that completion does not trust (``min_obs`` detections or more, but their
    projection disagrees with them or, with ``min_detected``, too few of their views detect them): a recurring false
    positive. Measurements: docs/tuning/infer_config.md#completeconfigdrop_untrusted."""
    max_fit_rel: float = bounded(1.0, gt=0, le=1)
    """A refitted track whose CAD model explains its masked depth worse than this (:attr:`WorldTrack.fit_rel`) is not
    trusted (a part of the structure taken for a valve); 1.0: off (the fit is capped). Measurements:
    docs/tuning/infer_config.md#completeconfigmax_fit_rel."""
    dedup_iou: float = bounded(0.5, gt=0, le=1)
    """A completion whose box overlaps a reported box of its class by at least this is not added."""
    reproject: bool = True
    """A completed track's detections report the visible box and mask of its world pose in their frame instead of the
    network's (a thin part's box often covers only its handle): box and pose then agree. Measurements:
    docs/tuning/infer_config.md#completeconfigreproject."""
    refit: RefitConfig = field(default_factory=RefitConfig)
    """Before completion, each track's world pose is fitted again to the masked depth of all its detections at once
    (:mod:`cadalign.infer.refine.track_fit`; tracks of at least ``min_obs`` detections), and a second track of the
    same part is dropped. Measurements: docs/tuning/infer_config.md#completeconfigrefit."""
    smooth: bool = True
    """A completed track's detections report its final world pose too (fused from all its frames, later ones included)
    instead of the running mean of the frames up to theirs. Measurements:
    docs/tuning/infer_config.md#completeconfigsmooth."""


@dataclass(frozen=True)
class InferConfig:
    refine: RefineConfig = field(default_factory=RefineConfig)
    """Refinement against the CAD (``refine.method = "none"`` keeps the network's pose)."""
    temporal: TemporalConfig = field(default_factory=TemporalConfig)
    """Temporal fusion over the video (``temporal.mode = "none"`` keeps per-frame poses)."""
    complete: CompleteConfig = field(default_factory=CompleteConfig)
    """Track completion after the video (:mod:`cadalign.infer.complete`): each static part fused in the world frame is
    reported wherever its pose puts it in sight, the detector's misses included; detections of short tracks are dropped.
    Measurements: docs/tuning/infer_config.md#inferconfigcomplete."""
    score_thresh: float = bounded(0.5, ge=0, le=1)
    """Detections scoring below this are dropped. Measurements: docs/tuning/infer_config.md#inferconfigscore_thresh."""
    class_score_thresh: dict[str, float] = field(default_factory=dict)
    """Per-class ``score_thresh`` (class name -> threshold) where it differs; the detector runs at the lowest of them
    all (:attr:`detector_score_thresh`). Measurements: docs/tuning/infer_config.md#inferconfigclass_score_thresh."""
    nms_iou: float = bounded(0.5, gt=0, le=1)
    """A trained network's detections (with those of its ``tiles`` windows) are non-maximum suppressed per class: of two
    same-class boxes overlapping by more than this IoU the lower-scoring goes (0.5, the network's own threshold, changes
    nothing without windows). Measurements: docs/tuning/infer_config.md#inferconfignms_iou."""
    tiles: TileConfig = field(default_factory=TileConfig)
    """Zoomed windows for a trained network (``tiles.zoom`` > 1; :class:`TileConfig`).
    Measurements: docs/tuning/infer_config.md#inferconfigtiles."""
    ignore_classes: tuple[str, ...] = ("background", "structure")
    """Classes not reported (the structure is what the parts sit on); ignored when it would leave nothing."""
    use_depth: bool = True
    """Use a depth map for ICP when one is given for the frame."""
    overlay: bool = True
    """Write ``overlay.mp4`` (CAD wireframe at each pose)."""
    overlay_fps: float = bounded(5.0, gt=0)
    """Frame rate of the overlay video."""
    reuse_box_iou: float = bounded(0.5, ge=0, le=1)
    """A detection whose box overlaps a same-class box of the previous frame by at least this IoU takes that detection's
    CAD model instead of being identified again (0 = off: identify every detection not on an established track, see
    ``track_init``). Measurements: docs/tuning/infer_config.md#inferconfigreuse_box_iou."""
    track_init: Literal["off", "model", "pose"] = "pose"
    """Frame-to-frame tracking: a detection on an established track of its class takes the track's CAD model (``model``)
    and also starts its refinement from the track's pose in this frame (``pose``) instead of the network's.
    Measurements: docs/tuning/infer_config.md#inferconfigtrack_init."""
    reidentify_growth: float = bounded(0.0, ge=0)
    """A detection on an established track (``track_init``) takes the track's CAD model, decided once by identification,
    mostly on the part's first and smallest or least visible views. Measurements:
    docs/tuning/infer_config.md#inferconfigreidentify_growth."""
    identify_iters: int = bounded(3, ge=0)
    """ICP iterations per candidate model (and yaw restart) when a detection's class has several models. Measurements:
    docs/tuning/infer_config.md#inferconfigidentify_iters."""
    identify_score: Literal["depth", "view"] = "depth"
    """How the candidate models of a detection are compared when its class has several and depth is given. Measurements:
    docs/tuning/infer_config.md#inferconfigidentify_score."""
    samples_per_model: int = bounded(3000, ge=100)
    """Surface samples per CAD model for ICP."""
    enhance: Literal["auto", "none", "clahe", "clahe_wb"] = "auto"
    """Pre-processing of each frame before detection (:func:`cadalign.sfm.frames.enhance`). 'auto': as the network's
    training images were prepared (:mod:`cadalign.sfm.image_prep`); the others force one. Measurements:
    docs/tuning/infer_config.md#inferconfigenhance."""

    def __post_init__(self) -> None:
        bad = {k: v for k, v in self.class_score_thresh.items() if not 0.0 <= float(v) <= 1.0}
        if bad:
            raise ValueError(f"class_score_thresh {bad}: each threshold must lie in [0, 1]")

    @property
    def detector_score_thresh(self) -> float:
        """The detector's own threshold: the lowest of ``score_thresh`` and the ``class_score_thresh`` values."""
        return min([self.score_thresh, *map(float, self.class_score_thresh.values())])


PRESETS: dict[str, InferConfig] = {
    "none": InferConfig(refine=REFINE_PRESETS["none"], temporal=TemporalConfig(mode="none")),
    "fast": InferConfig(refine=REFINE_PRESETS["fast"]),
    "balanced": InferConfig(),
    "accurate": InferConfig(refine=REFINE_PRESETS["accurate"], identify_iters=20, nms_iou=0.3,
                            reidentify_growth=1.5, complete=CompleteConfig(enabled=True)),
}

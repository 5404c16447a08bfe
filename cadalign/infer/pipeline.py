"""Per-frame pose inference: detector -> model identification -> refinement against the CAD -> temporal fusion.

:class:`PosePipeline` is the in-memory core (one frame in, :class:`PoseRecord` s and stage timings out);
:mod:`cadalign.infer.run` reads the video, writes ``poses.jsonl``, the overlay video, timings and, with
ground truth, the evaluation.

Model identification: a network reports a class, not which CAD model of that class it saw. When the
detection carries no ``obj_id`` and the class has several models, the model whose rendered silhouette at
the detected pose overlaps the predicted mask best (IoU) is taken.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from cadalign.cad.model import CadModel
from cadalign.config import bounded
from cadalign.formats.coco import mask_to_rle
from cadalign.geometry.compare import box_iou, mask_iou
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.complete import CompleteConfig, WorldTrack
from cadalign.infer.detect import Detector, TileConfig
from cadalign.infer.half_turn import view_disagreement, view_window
from cadalign.infer.hypotheses import yaw_hypotheses_rad
from cadalign.infer.model_geom import ModelGeometry, project_points, render_silhouette
from cadalign.infer.pose_math import Observation
from cadalign.infer.refine import PRESETS as REFINE_PRESETS
from cadalign.infer.refine import (
    RefineConfig,
    icp_points,
    pick_fit,
    refine,
    refine_depth_icp,
    refine_silhouette,
)
from cadalign.infer.temporal import TemporalConfig, TemporalFuser
from cadalign.infer.track_fit import (
    FittedTrack,
    RefitConfig,
    RefitResult,
    TrackPoints,
    TrackView,
    ViewScoring,
    duplicates,
    pick_model,
    refit_world_pose,
    turn_track,
)
from cadalign.metrics.pose import rotation_error_deg
from cadalign.types import Rigid3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class InferConfig:
    refine: RefineConfig = field(default_factory=RefineConfig)
    """Refinement against the CAD (``refine.method = "none"`` keeps the network's pose)."""
    temporal: TemporalConfig = field(default_factory=TemporalConfig)
    """Temporal fusion over the video (``temporal.mode = "none"`` keeps per-frame poses)."""
    complete: CompleteConfig = field(default_factory=CompleteConfig)
    """Track completion after the video (:mod:`cadalign.infer.complete`): each static part fused in the world frame is
    reported wherever its pose puts it in sight, the detector's misses included; detections of short tracks are dropped.
    Needs depth and the frames' camera poses, given (temporal mode ``world``) or registered on the parts (``ego``);
    without depth nothing changes. Default orbit, 33 held-out frames, true depth, ``accurate`` otherwise; valve / hot
    stab F1 without -> with completion (true camera poses; measured before ``complete.reproject`` and
    ``complete.refit``, whose numbers are in their docs), nine ``improved`` networks of sessions 19-21
    (training/pose_fast_zoom_*.toml, 4200-7600 steps): 0.817 -> 0.942 / 0.367 -> 0.695 (the acceptance network, seed 0),
    0.838 -> 0.959 / 0.386 -> 0.484 (seed 1), 0.866 -> 0.964 / 0.378 -> 0.525, 0.828 -> 0.844 / 0.358 -> 0.507 (two
    false valve tracks completed into 38 frames), 0.841 -> 0.952 / 0.296 -> 0.514, 0.790 -> 0.883 / 0.255 -> 0.756,
    0.828 -> 0.942 / 0.261 -> 0.659, 0.762 -> 0.850 / 0.239 -> 0.336, 0.812 -> 0.939 / 0.124 -> 0.550; ``thesis`` (seed
    0) 0.816 -> 0.867 / 0.349 -> 0.382. The misses left are parts never detected three times (the 87 mm panel valves at
    3-5 px, the UUV hot stab in its receptacle); ~20-30 ms per frame. Without camera poses (``ego``) seed 0 / 1: 0.817
    -> 0.893 / 0.367 -> 0.575 and 0.838 -> 0.883 / 0.386 -> 0.439 (``min_visible = 0.3``: 0.891 / 0.566 and 0.889 /
    0.477). On in ``accurate``."""
    score_thresh: float = bounded(0.5, ge=0, le=1)
    """Detections scoring below this are dropped. Default orbit, 33 held-out frames, ``accurate`` (with
    ``complete.refit``), true depth, 0.5 -> 0.3: seed 0 (4200 steps) valve / hot stab F1 0.970 / 0.813 -> 0.986 /
    0.947 (the UUV hot stab tracked from four 5 px detections, but fitted 60 deg off: hot stab R mean 0.20 -> 16.9
    deg); seed 1 0.972 / 0.798 -> 0.971 / 0.798 (valve R mean 0.98 -> 2.19 deg). Not taken."""
    class_score_thresh: dict[str, float] = field(default_factory=dict)
    """Per-class ``score_thresh`` (class name -> threshold) where it differs; the detector runs at the lowest of
    them all (:attr:`detector_score_thresh`). Empty in every preset. Default orbit, 33 held-out frames, true depth,
    ``accurate`` (with ``complete.refit.choose_model``), ``{"hot_stab": 0.3}`` (valve / hot stab F1, hot stab t /
    R mean): seed 2, 3700 steps 0.951 / 0.813, 0.006 m / 0.21 deg -> 0.951 / 0.984, 0.011 m / 2.26 deg (the UUV
    hot stab, never scored >= 0.5 there, tracked from 0.33-0.36 detections and completed: 30 of 30 at 6 deg); seed
    0, 3700 steps 0.917 / 1.000, 0.001 m / 0.65 deg -> 0.917 / 0.984, 0.002 m / 1.77 deg (a false hot stab track on
    the structure); ``thesis`` seed 0, 3700 steps 0.912 / 0.788, 0.011 m / 13.2 deg -> 0.912 / 0.769, 0.024 m /
    18.1 deg (28 more false hot stabs)."""
    nms_iou: float = bounded(0.5, gt=0, le=1)
    """A trained network's detections (with those of its ``tiles`` windows) are non-maximum suppressed per class:
    of two same-class boxes overlapping by more than this IoU the lower-scoring goes (0.5, the network's own
    threshold, changes nothing without windows). The networks' duplicates on thin parts overlap less than 0.5
    (a box on a hot stab's handle beside one on the whole part). Default orbit, 33 held-out frames, ``accurate``,
    true depth, 0.5 -> 0.3, valve / hot stab F1 of four networks (training/pose_fast_zoom_*.toml + amp): improved
    10000 steps 0.844 / 0.467 -> 0.856 / 0.466; improved 6600 steps seed 1 0.853 / 0.426 -> 0.860 / 0.463; thesis
    10000 steps 0.846 / 0.439 -> 0.862 / 0.442; improved with copy-paste 0.824 / 0.304 -> 0.835 / 0.331; poses
    unchanged within noise. 0.3 in ``accurate``; the other presets keep the network's 0.5 (only measured there)."""
    tiles: TileConfig = field(default_factory=TileConfig)
    """Zoomed windows for a trained network (``tiles.zoom`` > 1; :class:`~cadalign.infer.detect.TileConfig`). Off
    in every preset: on the default orbit (as ``nms_iou``, with it at 0.3) ``zoom = 1.6`` (4 windows, ~5x the
    detector's time) and windows' detections kept from 0.8 moved valve / hot stab F1 by +0.027 / +0.031
    (improved, 10000 steps), -0.011 / -0.026 (improved, 6600 steps seed 1), +0.008 / -0.004 (thesis, 10000
    steps): recall rises (with the windows' detections kept from 0.5: valve 0.78-0.79 -> 0.85, hot stab 0.44 ->
    0.51-0.57), and so do false positives, mostly 2-4 px boxes on 1-3 px panel valves and boxes on a hot stab's
    handle alone. Session 14 found the same of the whole frame upscaled 1.5x / 2x."""
    ignore_classes: tuple[str, ...] = ("background", "structure")
    """Classes not reported (the structure is what the parts sit on); ignored when it would leave nothing."""
    use_depth: bool = True
    """Use a depth map for ICP when one is given for the frame."""
    overlay: bool = True
    """Write ``overlay.mp4`` (CAD wireframe at each pose)."""
    overlay_fps: float = bounded(5.0, gt=0)
    """Frame rate of the overlay video."""
    reuse_box_iou: float = bounded(0.5, ge=0, le=1)
    """A detection whose box overlaps a same-class box of the previous frame by at least this IoU takes that
    detection's CAD model instead of being identified again (0 = off: identify every detection not on an
    established track, see ``track_init``). Added when the only reuse was a 3D gate on the network's translation
    (~1 m off), which met 6 of 263 detections on the default scene's 33 held-out frames. There, 2 threads:
    'fast' 522 -> 474 ms/frame, accuracy unchanged; 'balanced' with 4 yaw restarts 1375 -> 1067 ms/frame and
    refined valve rotation error 16.3 -> 13.4 deg mean."""
    track_init: Literal["off", "model", "pose"] = "pose"
    """Frame-to-frame tracking. A detection whose box holds the projected centre of an established track of its
    class (fused from at least three frames; with depth, the masked depth within half the part's diameter of that
    centre) takes the track's CAD model instead of being identified again (``model``), and (``pose``) starts its
    refinement from the track's pose in this frame instead of the network's (~1 m and tens of degrees off at 10 m).
    ``off``: identify every detection not reused by ``reuse_box_iou``. (Until session 14 a 3D gate of the
    network's translation against the tracks also reused models. Removing it left the 6600-step ``improved``
    network's held-out results unchanged; the ``thesis`` network's translations (~0.5 m off) met it more often,
    and its fused valve rotation error went 56.2 -> 51.2 deg without it.)
    Default orbit, 33 held-out frames, ``accurate`` before ``refine.tie_m``, true camera poses; fused valve R mean
    (without the ball valve) / t mean / ms per frame (2 threads): 3300-step network off 3.52 (3.36) deg / 0.026 m /
    2208; model 3.44 (3.91) / 0.026 / 1171; pose 2.67 (3.05) / 0.025 / 1128. 6600-step network off 7.23 (2.28) /
    0.049 / 2160; model 5.90 (1.80) / 0.048 / 1116; pose 12.75 (1.53) / 0.003 / 1087. Without the ball valve,
    ``pose`` is the best every time; the ball valve (no symmetry, but its lever the only difference from a half
    turn) was a coin toss at 10-13 m, and ``pose`` keeps the orientation of its first frames (right for one network,
    flipped for 11 of 28 detections with the other), where ``off`` / ``model`` fuse independent per-frame guesses.
    With ``tie_m`` (the start wins ties) the 6600-step network's ``pose`` run gives 1.12 deg / 0.009 m."""
    reidentify_growth: float = bounded(0.0, ge=0)
    """A detection on an established track (``track_init``) takes the track's CAD model, decided once by
    identification, mostly on the part's first and smallest or least visible views. With this > 0, when a
    detection's mask has at least this many times the pixels of the largest mask the track's model was
    identified on, the detection is identified again (from the track's pose): the same model raises the bar, another
    retires the track and starts a new one with that model. 0: never. Default orbit, 33 held-out frames: one
    gate valve, identified at 39 % visibility in its first frames as the ball valve, kept that model on all its
    28-30 later detections, fully visible at 9-12 m, which identification alone gets right. There (``accurate``
    otherwise, true depth), 0 -> 1.5, fused valve R mean / wrong-model valve detections / fused hot stab t and R
    mean: ``improved`` 10000 steps 4.82 -> 3.76 deg / 33 -> 11 / 0.264 m, 34.8 deg -> 0.167 m, 31.2 deg; its seed 1
    1.17 -> 0.92 / 34 -> 11 / 0.102, 28.1 -> 0.034, 11.2; 6600 steps seed 1 6.34 -> 1.30 / 30 -> 6 / 0.211, 44.8 ->
    0.142, 42.0; with copy-paste 0.62 -> 0.67 / 32 -> 10 / 0.367, 46.2 -> 0.342, 39.2. ``thesis`` 10000 steps
    36.7 -> 24.5 / 63 -> 40 / 0.173, 68.3 -> 0.166, 57.3; its seed 1 32.1 -> 25.2 / 36 -> 30 / 0.263, 72.9 ->
    0.289, 103.1. One to three re-identifications changed a model per run; time per frame unchanged. 1.5 in
    ``accurate``."""
    identify_iters: int = bounded(3, ge=0)
    """ICP iterations per candidate model (and yaw restart) when a detection's class has several models. Three
    leave every big valve type of the default scene 10-18 mm (median point distance) from the ball valve's
    points at 10 m, so the pick among them is noise; 20 converge, and the right type fits best. The default
    orbit's 33 held-out frames, 4 yaw restarts: fused valve rotation error 9.7 (3) -> 4.2 (10) -> 3.4 deg (20)
    mean, 1.7x the time per frame (the ball valve taken for another type in 6 of its 27 detections -> 1).
    Giving the 3-iteration fits' best 3 (or 12) 17 more iterations instead gave 11.3 (3.8) deg: the right type
    is often not among the best after three."""
    identify_score: Literal["depth", "view"] = "depth"
    """How the candidate models of a detection are compared when its class has several and depth is given.
    ``depth``: the smallest median distance of the masked depth points to the model (data -> model). ``view``:
    each model's best-fitting yaw restart (as ``depth``, ties within ``refine.tie_m``) is scored from the model's
    side too, as the half-turn check scores a pose (:func:`cadalign.infer.half_turn.view_disagreement`: pixels seen
    through the model plus mask pixels it leaves unexplained), and the model disagreeing in fewest pixels wins
    (within ``refine.half_turn_min_px`` of it, the best depth fit). The data -> model fit cannot see model surface
    where nothing was observed: a decoy holding the whole part plus more fits as well. Default orbit, 33 held-out
    frames, ``accurate`` otherwise (with ``reidentify_growth``), true depth, four ``improved`` networks
    (training/pose_fast_zoom_improved.toml + amp: 10000 steps seeds 0 and 1, 6600 steps seed 1, with copy-paste):
    ``depth`` -> ``view`` took the wrong valve model in 15 instead of 38 of 689 matched detections (fused valve R
    mean 1.66 -> 1.50 deg), but hot stabs came out worse (fused t 0.171 -> 0.188 m, R 30.9 -> 34.7 deg mean):
    their masks often cover the handle alone, which the other hot stab model explains as well. ``depth`` in every
    preset."""
    samples_per_model: int = bounded(3000, ge=100)
    """Surface samples per CAD model for ICP."""
    enhance: Literal["auto", "none", "clahe", "clahe_wb"] = "auto"
    """Pre-processing of each frame before detection, as :func:`cadalign.sfm.frames.enhance`. 'auto': as the
    network's training images were prepared (:mod:`cadalign.sfm.image_prep`: a built dataset's images were
    CLAHE-enhanced by SfM, a simulator's are raw), read from the run folder; the others force one (default CLAHE
    settings). Measured on the default scene's 16 held-out frames: valve F1 0.902 on the dataset's images, 0.676
    on the raw frames. The overlay is drawn on the raw frame."""

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


@dataclass(frozen=True)
class PoseRecord:
    """One reported instance of one frame (a line of ``poses.jsonl``)."""

    frame: int
    frame_name: str
    obj_id: int | None
    track_id: int
    label: int
    class_name: str
    score: float
    box_xyxy: np.ndarray
    T_cam_from_obj: Rigid3
    """The reported pose: refined and temporally fused."""
    T_detector: Rigid3
    """The detector's pose."""
    T_refined: Rigid3
    """After refinement, before temporal fusion."""
    refine_iters: dict[str, int]
    mask: np.ndarray | None = None
    """(H, W) bool from the detector (a :class:`~cadalign.metrics.pose_eval.CroppedMask` once stored for evaluation)."""
    source: str = "detector"
    """``detector``: a detection of this frame; ``track``: added by track completion (:mod:`cadalign.infer.complete`),
    the track's world pose projected into a frame where the detector missed the part."""
    box_detector: np.ndarray | None = None
    """The network's box where ``box_xyxy`` reports another (track completion's ``reproject``); None: they are the
    same."""

    def to_json(self) -> dict:
        return {
            "frame": self.frame, "frame_name": self.frame_name, "obj_id": self.obj_id, "track_id": self.track_id,
            "class": self.class_name, "label": self.label, "score": round(float(self.score), 6),
            "box_xyxy": _box_json(self.box_xyxy),
            "T_cam_from_obj": self.T_cam_from_obj.matrix().tolist(),
            "T_cam_from_obj_detector": self.T_detector.matrix().tolist(),
            "T_cam_from_obj_refined": self.T_refined.matrix().tolist(),
            "refine_iters": self.refine_iters,
            "mask_rle": mask_to_rle(self.mask) if isinstance(self.mask, np.ndarray) else None,
            "source": self.source,
            "box_xyxy_detector": None if self.box_detector is None else _box_json(self.box_detector),
        }


def _box_json(box: np.ndarray) -> list[float]:
    return [round(float(v), 3) for v in box]


class PosePipeline:
    """Detector -> identification -> refinement -> temporal fusion, one frame at a time (state: the tracks)."""

    def __init__(self, detector: Detector, models: dict[int, CadModel], class_names: tuple[str, ...],
                 cfg: InferConfig) -> None:
        self.detector, self.models, self.class_names, self.cfg = detector, models, tuple(class_names), cfg
        self._geoms: dict[int, ModelGeometry] = {}
        kept = [n for n in self.class_names if n not in cfg.ignore_classes]
        self.ignored = set(cfg.ignore_classes) if kept else set()
        self.fuser = TemporalFuser(cfg.temporal)
        self._prev: tuple[int, list[tuple[int, np.ndarray, int]]] | None = None
        """(frame, [(label, box_xyxy, obj_id)]) of the last processed frame, for ``reuse_box_iou``."""
        refit = cfg.complete.refit
        self.points = TrackPoints(refit) if cfg.complete.enabled and refit.enabled and cfg.use_depth else None
        """World-frame masked depth points per track, for the refit of its world pose before completion."""

    def geometry(self, obj_id: int) -> ModelGeometry:
        if obj_id not in self._geoms:
            self._geoms[obj_id] = ModelGeometry.from_cad(self.models[obj_id], self.cfg.samples_per_model,
                                                         self.cfg.refine.seed)
        return self._geoms[obj_id]

    def world_tracks(self) -> list[WorldTrack]:
        """The tracks fused in a world frame (given or ego camera poses) that have a CAD model, for completion; with
        ``complete.refit`` the world pose of each track of at least ``complete.min_obs`` detections is fitted
        again to all its points, and duplicates among them are marked (:mod:`cadalign.infer.track_fit`).

        Retired tracks are among them when refitted (an ego world left behind, or a model re-identified: with the
        refit, whichever of the old and the new track lies closer to both tracks' points is kept)."""
        out, fitted = [], []
        for tr in self.fuser.tracks:
            space = tr.retired_from if tr.space == "retired" else tr.space
            if space in ("world", "ego") and tr.obj_id is not None:
                f = self._refit(tr.track_id, tr.label, tr.obj_id, tr.world, tr.T)
                if f is None and tr.space == "retired":
                    continue
                if f is not None:
                    fitted.append(f)
                out.append(WorldTrack(tr.track_id, tr.label, tr.obj_id if f is None else f.obj_id,
                                      tr.T if f is None else f.T_world_from_obj, tr.world,
                                      fit_rel=None if f is None else f.fit_rel))
        dup = duplicates(fitted, self.cfg.complete.refit)
        for k, j in dup.items():
            log.info("track %d duplicates track %d (that track's pose explains its points)", k, j)
        return [replace(w, duplicate_of=dup.get(w.track_id)) for w in out]

    def _refit(self, track_id: int, label: int, obj_id: int, world: int, T: Rigid3) -> FittedTrack | None:
        """A track's world pose fitted to all its points (``complete.refit``), None when it is not refitted (off,
        fewer than ``complete.min_obs`` detections with points, or too few points). With ``refit.choose_model``
        every model of its class is fitted and the best kept (:func:`~cadalign.infer.track_fit.pick_model`)."""
        n = self.points.frames(track_id) if self.points is not None else 0
        if self.points is None or n < self.cfg.complete.min_obs:
            return None
        P, C = self.points.of(track_id)
        cfg = self.cfg.complete.refit
        views = self.points.views(track_id) if cfg.choose_model == "view" else ()
        near_m = max(self.geometry(m).diameter_m for m in self.candidates(label)) if views else 0.0

        def scoring(m: int, near: float) -> ViewScoring:
            """How model ``m``'s poses are scored against the views (half-turn check's tolerances)."""
            g = self.geometry(m)
            return ViewScoring(self.cfg.refine.half_turn_tol * g.diameter_m, self.cfg.refine.half_turn_band_px,
                               max(near, g.diameter_m), cfg.mask_weight)

        def fit(m: int, c: RefitConfig) -> RefitResult | None:
            return refit_world_pose(self.geometry(m), T, P, C, c, self.models[m].symmetry, views, scoring(m, near_m))

        own = fit(obj_id, cfg)
        if own is None:  # too few points: the same for every model
            return None
        fits, k = {obj_id: own}, obj_id
        others = [m for m in self.candidates(label) if m != obj_id] if cfg.choose_model != "off" else []
        if others:
            quick = cfg.screening() if cfg.screen else cfg
            for m in others:
                r = fit(m, quick)
                if r is not None:
                    fits[m] = r
            k = self._pick_model(track_id, fits, P, obj_id)
            if k != obj_id and cfg.screen:  # the winner of the cheap search, fitted in full, against the own fit
                full = fit(k, cfg)
                fits = {obj_id: own, k: full or fits[k]}
                k = self._pick_model(track_id, fits, P, obj_id)
        r = fits[k]
        turned_deg = 0.0
        if cfg.choose_model == "view" and cfg.view_turns_deg:
            T_turned = turn_track(self.geometry(k), r.T_world_from_obj, P, C, views, cfg,
                                  scoring(k, max(self.geometry(m).diameter_m for m in fits)))
            turned_deg = rotation_error_deg(T_turned.R, r.T_world_from_obj.R)
            r = replace(r, T_world_from_obj=T_turned)
        log.info("track %d (model %d): refit on %d frames, %d points: fit %.1f mm (fused pose %.1f mm), "
                 "moved %.3f m%s%s", track_id, obj_id, n, len(P), 1e3 * r.fit_m, 1e3 * fits[obj_id].fused_fit_m,
                 float(np.linalg.norm(r.T_world_from_obj.t - T.t)), "" if k == obj_id else f", now model {k}",
                 f", then turned {turned_deg:.1f} deg by its views" if turned_deg > 0 else "")
        return FittedTrack(track_id, label, world, n, self.geometry(k), r.T_world_from_obj, P, k, r.fit_m)

    def _pick_model(self, track_id: int, fits: dict[int, RefitResult], P: np.ndarray, own: int) -> int:
        """:func:`~cadalign.infer.track_fit.pick_model` of a track's fitted models (its views with ``choose_model =
        "view"``)."""
        cfg = self.cfg.complete.refit
        views = self.points.views(track_id) if self.points is not None and cfg.choose_model == "view" else ()
        return pick_model({m: r.T_world_from_obj for m, r in fits.items()}, {m: self.geometry(m) for m in fits}, P,
                          own, cfg.model_margin, views, self.cfg.refine.half_turn_tol,
                          self.cfg.refine.half_turn_band_px, cfg.model_min_px, cfg.mask_weight)

    def candidates(self, label: int) -> list[int]:
        name = self.class_names[label] if 0 <= label < len(self.class_names) else ""
        return [k for k, m in sorted(self.models.items()) if m.class_name == name]

    def identify(self, det: object, T: Rigid3, K: np.ndarray,
                 depth_m: np.ndarray | None = None) -> tuple[int | None, Rigid3]:
        """The CAD model of a detection and a start pose for its refinement.

        The detection's ``obj_id`` or the only model of its class; else each candidate is refined briefly
        (``identify_iters``) and the best fit wins: the smallest median distance of the masked depth points
        to the model when depth is given, else the largest silhouette IoU with the mask. On the default
        scene's oracle detections (3 cm / 3 deg noise) this picks the right valve type in 94 of 104 cases
        with depth and 92 of 104 by silhouette IoU. With ``refine.yaw_hypotheses`` > 1 each candidate is also
        tried from the yaw restarts of :func:`cadalign.infer.hypotheses.yaw_hypotheses_rad`: from a network's
        45-65 deg yaw error three ICP iterations fit the wrong valve type as well as the right one.
        """
        oid = getattr(det, "obj_id", None)
        if oid is not None and oid in self.models:
            return int(oid), T
        cands = self.candidates(int(det.label))
        if len(cands) <= 1:
            return (cands[0] if cands else None), T
        mask = np.asarray(det.mask, bool)
        if not mask.any():
            return cands[0], T
        cfg = self.cfg.refine
        n = self.cfg.identify_iters
        Q = icp_points(depth_m, mask, K, cfg) if depth_m is not None else None
        use_depth = Q is not None and len(Q) >= cfg.min_depth_points and cfg.method in ("depth", "both")
        scored = []
        for k in cands:
            g = self.geometry(k)
            if use_depth:  # from each yaw restart (refine.yaw_hypotheses) the model's symmetry leaves distinct
                for yaw in yaw_hypotheses_rad(cfg.yaw_hypotheses, self.models[k].symmetry):
                    T_h = Rigid3(T.R @ axis_angle_to_matrix(np.array([0.0, 0.0, yaw])), T.t) if yaw else T
                    Tk = refine_depth_icp(g, T_h, K, depth_m, mask, cfg, iters=n)[0]
                    d, _ = g.tree.query(Tk.inverse().apply(Q))
                    scored.append((float(np.median(d)), k, Tk))  # not capped: that would favour small models
            else:  # with refinement off, the detector's pose is scored as it is
                Tk = refine_silhouette(g, T, K, mask, cfg, iters=n)[0] if cfg.method in ("silhouette", "both") else T
                scored.append((-_window_iou(g, Tk, K, mask), k, Tk))
        if use_depth and self.cfg.identify_score == "view":
            return self._pick_model_by_view(scored, T, K, mask, depth_m)
        _, best, T_best = scored[pick_fit([x[0] for x in scored], [x[2] for x in scored], T,
                                          cfg.tie_m if use_depth else 0.0)]
        return best, T_best

    def _pick_model_by_view(self, scored: list[tuple[float, int, Rigid3]], T: Rigid3, K: np.ndarray,
                            mask: np.ndarray, depth_m: np.ndarray) -> tuple[int, Rigid3]:
        """``identify_score = "view"``: per model its best depth fit's pose, then the model whose pose disagrees
        with the view in fewest pixels (ties within ``refine.half_turn_min_px``: the best depth fit). A mask pixel
        counts as the object's within the largest candidate's diameter of the median masked depth, for every
        model alike."""
        cfg = self.cfg.refine
        per_model: dict[int, tuple[float, Rigid3]] = {}
        for k in dict.fromkeys(x[1] for x in scored):
            mine = [x for x in scored if x[1] == k]
            i = pick_fit([x[0] for x in mine], [x[2] for x in mine], T, cfg.tie_m)
            per_model[k] = (mine[i][0], mine[i][2])
        boxes = np.array([view_window(self.geometry(k), [Tk], K, mask) for k, (_, Tk) in per_model.items()])
        win = (int(boxes[:, 0].min()), int(boxes[:, 1].min()), int(boxes[:, 2].max()), int(boxes[:, 3].max()))
        z = depth_m[mask]
        z = z[np.isfinite(z) & (z > 0)]
        near = (float(np.median(z)), max(self.geometry(k).diameter_m for k in per_model)) if len(z) else None
        view = {k: view_disagreement(self.geometry(k), Tk, K, mask, depth_m,
                                     cfg.half_turn_tol * self.geometry(k).diameter_m, win, cfg.half_turn_band_px,
                                     near) for k, (_, Tk) in per_model.items()}
        least = min(view.values())
        best = min((k for k in per_model if view[k] <= least + cfg.half_turn_min_px), key=lambda k: per_model[k][0])
        return best, per_model[best][1]

    def _reused_model(self, det: object, frame: int) -> int | None:
        """The model id of the previous frame's same-class detection whose box this one overlaps most (IoU >=
        ``reuse_box_iou``, consecutive frames only), for a class with several models; else None."""
        if getattr(det, "obj_id", None) is not None or self.cfg.reuse_box_iou <= 0 or self._prev is None \
                or self._prev[0] != frame - 1:
            return None
        label = int(det.label)
        prev = [(box, k) for lab, box, k in self._prev[1] if lab == label]
        if len(self.candidates(label)) <= 1 or not prev:
            return None
        ious = box_iou(np.asarray(det.box_xyxy, float), np.stack([b for b, _ in prev]))[0]
        best = int(np.argmax(ious))
        return prev[best][1] if ious[best] >= self.cfg.reuse_box_iou else None

    def _track_start(self, det: object, K: np.ndarray, frame: int, T_world_from_cam: Rigid3 | None,
                     depth_m: np.ndarray | None, taken: set[int]) -> tuple[int, Rigid3, int, int] | None:
        """(model id, start pose, track id, the track's ``id_px``) from the established track under a detection
        (``track_init``), else None.

        The track's model centre must project into the detection's box (the nearest to the box centre wins), and
        with depth lie within half the part's diameter of the median depth in the mask; ``taken`` holds the tracks
        (ids) earlier detections of this frame took."""
        if self.cfg.track_init == "off" or getattr(det, "obj_id", None) is not None:
            return None
        z_obs = None
        if depth_m is not None and det.mask is not None:
            z = depth_m[np.asarray(det.mask, bool)]
            z = z[np.isfinite(z) & (z > 0)]
            z_obs = float(np.median(z)) if len(z) else None
        x0, y0, x1, y1 = np.asarray(det.box_xyxy, float)
        best = None
        for j, oid, T, id_px in self.fuser.track_views(int(det.label), frame, T_world_from_cam):
            if j in taken or oid not in self.models:
                continue
            c = T.apply(self.geometry(oid).samples.mean(0)[None])
            if c[0, 2] <= 1e-6:
                continue
            u, v = project_points(K, c)[0]
            if not (x0 <= u <= x1 and y0 <= v <= y1):
                continue
            if z_obs is not None and abs(z_obs - c[0, 2]) > 0.5 * self.models[oid].diameter_m:
                continue
            dist = float(np.hypot(u - (x0 + x1) / 2, v - (y0 + y1) / 2))
            if best is None or dist < best[0]:
                best = (dist, j, oid, T, id_px)
        if best is None:
            return None
        taken.add(best[1])
        return best[2], best[3], best[1], best[4]

    def _start(self, d: object, T0: Rigid3, K: np.ndarray, frame: int, T_world_from_cam: Rigid3 | None,
               depth: np.ndarray | None, taken: set[int]) -> tuple[int | None, Rigid3, int]:
        """(model id, start pose of the refinement, ``id_px``: the mask's pixels when identification chose the
        model, else 0) of a detection: from its track, the previous frame's box, or identification."""
        px = int(np.count_nonzero(d.mask)) if getattr(d, "mask", None) is not None else 0
        start = self._track_start(d, K, frame, T_world_from_cam, depth, taken)
        if start is None:
            oid = self._reused_model(d, frame)
            if oid is not None:
                return oid, T0, 0
            oid, T = self.identify(d, T0, K, depth)
            return oid, T, px if len(self.candidates(int(d.label))) > 1 else 0
        oid, T_track, track_id, id_px = start
        T_start = T_track if self.cfg.track_init == "pose" else T0
        growth = self.cfg.reidentify_growth
        if growth <= 0 or len(self.candidates(int(d.label))) <= 1 or px < growth * max(id_px, 1):
            return oid, T_start, 0
        oid_new, T_new = self.identify(d, T_start, K, depth)
        if oid_new is None or oid_new == oid:
            self.fuser.note_identified(track_id, px)
            return oid, T_start, 0
        log.info("frame %d: track %d re-identified as model %d (was %d) on a %d px mask", frame, track_id, oid_new,
                 oid, px)
        self.fuser.retire(track_id)
        return oid_new, T_new, px

    def process(self, frame: int, name: str, image: np.ndarray, K: np.ndarray, depth_m: np.ndarray | None = None,
                T_world_from_cam: Rigid3 | None = None) -> tuple[list[PoseRecord], dict[str, float]]:
        """Poses of one frame and the seconds spent per stage.

        ``detector`` (the whole ``detect`` call; a network's own split, e.g. its pose head, as ``detector.*``),
        ``identify`` (which CAD model), ``refinement``, ``temporal``.
        """
        K = np.asarray(K, dtype=np.float64)
        t0 = time.perf_counter()
        if hasattr(self.detector, "for_frame"):
            self.detector.for_frame(name)
        dets = self.detector.detect(image, K)
        t1 = time.perf_counter()
        times = {"detector": t1 - t0, "identify": 0.0, "refinement": 0.0, "temporal": 0.0}
        times.update({f"detector.{k}": v for k, v in (getattr(self.detector, "last_timings", None) or {}).items()})
        kept, taken = [], set()
        for d in dets:
            name_c = self.class_names[int(d.label)] if 0 <= int(d.label) < len(self.class_names) else "?"
            if float(d.score) < self.cfg.class_score_thresh.get(name_c, self.cfg.score_thresh) \
                    or name_c in self.ignored:
                continue
            ta = time.perf_counter()
            T0 = Rigid3(np.asarray(d.R_cam_from_obj, float), np.asarray(d.t_cam_from_obj_m, float))
            depth = depth_m if self.cfg.use_depth else None
            oid, T_start, id_px = self._start(d, T0, K, frame, T_world_from_cam, depth, taken)
            tb = time.perf_counter()
            times["identify"] += tb - ta
            if oid is None:
                log.warning("frame %s: no CAD model of class %r; detection dropped", name, name_c)
                continue
            res = refine(self.geometry(oid), T_start, K, np.asarray(d.mask, bool), self.cfg.refine, depth,
                         self.models[oid].symmetry)
            times["refinement"] += time.perf_counter() - tb
            kept.append((d, oid, name_c, T0, res, id_px))
        self._prev = (frame, [(int(d.label), np.asarray(d.box_xyxy, float), oid) for d, oid, *_ in kept])
        ta = time.perf_counter()
        obs = [Observation(int(d.label), res.T_cam_from_obj, oid, self.models[oid].symmetry,
                           self.models[oid].diameter_m, id_px) for d, oid, _, _, res, id_px in kept]
        fused = self.fuser.update(frame, obs, T_world_from_cam)
        world, T_wc = self.fuser.cameras.get(frame, (None, None))
        if self.points is not None and depth_m is not None and T_wc is not None \
                and (world == 0 or self.cfg.complete.refit.ego):  # world 0: the given camera poses
            refit = self.cfg.complete.refit
            for (d, *_), f in zip(kept, fused, strict=True):
                if f.track_id >= 0:
                    mask = np.asarray(d.mask, bool)
                    view = TrackView.crop(K, T_wc, mask, depth_m, refit.view_pad) \
                        if refit.choose_model == "view" else None
                    self.points.add(f.track_id, icp_points(depth_m, mask, K, self.cfg.refine), T_wc, view)
        times["temporal"] = time.perf_counter() - ta  # with the points kept for the track refit
        records = [PoseRecord(frame, name, oid, f.track_id, int(d.label), name_c, float(d.score),
                              np.asarray(d.box_xyxy, float), f.T_cam_from_obj, T0, res.T_cam_from_obj,
                              dict(res.iterations), np.asarray(d.mask, bool))
                   for (d, oid, name_c, T0, res, _), f in zip(kept, fused, strict=True)]
        return records, times


def _window_iou(geom: ModelGeometry, T: Rigid3, K: np.ndarray, mask: np.ndarray) -> float:
    """Silhouette IoU with ``mask`` inside the mask's box grown by half its size on each side."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    h, w = rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1
    x0, y0 = max(int(cols[0] - w // 2), 0), max(int(rows[0] - h // 2), 0)
    win = mask[y0:y0 + 2 * h, x0:x0 + 2 * w]
    return mask_iou(render_silhouette(geom, T, K, win.shape, (x0, y0)), win)

"""Track completion: a second pass over a video that reports each static part wherever its fused pose says it is in
view, including the frames in which the detector missed it, and drops the detections no track confirms.

A part fused in a world frame has one pose for the whole video: the world of the frames' given camera poses (e.g.
from SfM; temporal mode ``world``), or that of the camera poses registered on the parts themselves (``ego``; a
frame that registers no part gets no completion). Projected into any frame, it gives the part's box, mask and pose
there; the frame's depth map tells which of its pixels are in sight (a model point is seen where it is no farther
than the observed depth plus a tolerance), so parts hidden behind others are not reported. Before this pass, the
pipeline fits each track's world pose again to the masked depth of all its detections (``refit``,
:mod:`cadalign.infer.refine.track_fit`) and marks a track that another explains as its duplicate (``duplicate_of``).
A track is completed only when

- it holds at least ``min_obs`` detections (a part the network saw once or twice may be a false positive), and
- its world pose, projected into its own frames, agrees with its detections (the median box IoU of its visible
  projection and its detections is at least ``consistency_iou``): a track fused from poses that disagree (a hot
  stab's spin or a wrong model) would put boxes where the part is not;
- optionally, it was detected in at least ``min_detected`` of the frames its projection shows in sight.

A duplicate of a completed track is dropped with its detections. Completed records carry ``source = "track"``, the
track's CAD model, its median detection score and the projected pose (with ``smooth``, the track's own detections
report that world pose as well, and with ``reproject`` the box and mask it projects to, so that a record's box and
pose agree); a completion overlapping a reported box of its class (``dedup_iou``) is not added (the part is already
there, often as another track of the same part). With ``drop_short``, detections of tracks shorter than ``min_obs``
are dropped from the report.

Frames without depth (or pixels with no valid depth) show nothing: no completion is made where visibility cannot be
checked.
"""

from __future__ import annotations

import math
from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from cadalign.geometry.compare import box_iou
from cadalign.infer.config import CompleteConfig
from cadalign.infer.model_geom import ModelGeometry, project_points, render_depth
from cadalign.metrics.pose_eval import CroppedMask
from cadalign.types import Rigid3


@dataclass(frozen=True)
class WorldTrack:
    """What completion needs of a fused track: its id, class, CAD model and world pose."""

    track_id: int
    label: int
    obj_id: int
    T_world_from_obj: Rigid3
    world: int = 0
    """Which world the pose is in (:attr:`cadalign.infer.temporal.TemporalFuser.cameras`)."""
    duplicate_of: int | None = None
    """The track this one duplicates (the same part: :func:`cadalign.infer.refine.track_fit.duplicates`); when that
    one is completed, this one's detections are dropped and it is not completed."""
    fit_rel: float | None = None
    """How well its CAD model explains its masked depth after the refit
    (:attr:`cadalign.infer.refine.track_fit.FittedTrack.fit_rel`); None when it was not refitted."""


@dataclass(frozen=True)
class Projection:
    """A part's visible projection in one frame: pose, visible box (x0, y0, x1, y1 px) and visible mask."""

    T_cam_from_obj: Rigid3
    box_xyxy: np.ndarray
    mask: CroppedMask


def project_visible(geom: ModelGeometry, T_cam_from_obj: Rigid3, K: np.ndarray, depth_m: np.ndarray,
                    cfg: CompleteConfig, near_m: float = 0.05) -> Projection | None:
    """The part's pixels in sight in a frame of depth ``depth_m`` (H, W) metres, or None.

    None when a model vertex is nearer than ``near_m`` to the camera plane (behind or at the camera), when the
    model projects outside the frame, or when less than ``cfg.min_visible`` of its silhouette is in sight. Pixels
    whose observed depth is not finite or not positive count as not in sight.
    """
    H, W = depth_m.shape
    X = geom.vertices @ T_cam_from_obj.R.T + T_cam_from_obj.t
    if len(X) == 0 or X[:, 2].min() <= near_m:
        return None
    uv = project_points(K, X)
    x0, y0 = max(math.floor(uv[:, 0].min()) - 1, 0), max(math.floor(uv[:, 1].min()) - 1, 0)
    x1, y1 = min(math.ceil(uv[:, 0].max()) + 1, W), min(math.ceil(uv[:, 1].max()) + 1, H)
    if x1 <= x0 or y1 <= y0:
        return None
    z = render_depth(geom, T_cam_from_obj, K, (y1 - y0, x1 - x0), (x0, y0))
    sil = np.isfinite(z)
    n_sil = int(np.count_nonzero(sil))
    if n_sil == 0:
        return None
    obs = depth_m[y0:y1, x0:x1]
    valid = np.isfinite(obs) & (obs > 0)
    with np.errstate(invalid="ignore"):
        tol = np.maximum(cfg.depth_tol_m, cfg.depth_tol_rel * np.where(sil, z, 0.0))
        seen = sil & valid & (z <= np.where(valid, obs, 0.0) + tol)
    if np.count_nonzero(seen) < cfg.min_visible * n_sil or not seen.any():
        return None
    rows, cols = np.flatnonzero(seen.any(1)), np.flatnonzero(seen.any(0))
    box = np.array([x0 + cols[0], y0 + rows[0], x0 + cols[-1] + 1, y0 + rows[-1] + 1], float)
    crop = seen[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1].copy()
    return Projection(T_cam_from_obj, box, CroppedMask(crop, int(x0 + cols[0]), int(y0 + rows[0])))


@dataclass
class _Candidate:
    frame: int
    name: str
    proj: Projection


@dataclass
class TrackCompleter:
    """The completion pass: feed every frame to :meth:`frame`, then take :meth:`result`.

    ``records``: the video's per-frame records (:class:`~cadalign.infer.pipeline.PoseRecord`, or any frozen
    dataclass with ``frame``, ``frame_name``, ``track_id``, ``label``, ``class_name``, ``obj_id``, ``score``,
    ``box_xyxy``, ``T_cam_from_obj``, ``T_detector``, ``T_refined``, ``refine_iters``, ``mask``, ``source`` and
    ``box_detector``);
    ``geometry``: the :class:`ModelGeometry` of a CAD model id.
    """

    cfg: CompleteConfig
    tracks: Sequence[WorldTrack]
    records: Sequence[Any]
    geometry: Callable[[int], ModelGeometry]
    _n: Counter = field(init=False)
    _by_frame: dict = field(init=False)
    _ious: dict = field(init=False)
    _cands: dict = field(init=False)
    _cams: dict = field(init=False)
    _own: dict = field(init=False)
    _fit: dict = field(init=False)

    def __post_init__(self) -> None:
        self._n = Counter(r.track_id for r in self.records)
        self._by_frame = defaultdict(dict)
        for r in self.records:
            self._by_frame[r.frame_name][r.track_id] = r
        self.tracks = [t for t in self.tracks if self._n[t.track_id] >= self.cfg.min_obs]
        self._fit = {t.track_id: t.fit_rel for t in self.tracks}
        self._ious = defaultdict(list)
        self._cands = defaultdict(list)
        self._cams = {}
        self._own = {}

    def frame(self, index: int, name: str, K: np.ndarray, T_world_from_cam: Rigid3 | None,
              depth_m: np.ndarray | None, world: int = 0) -> None:
        """Project every eligible track of ``world`` into one frame (nothing without a camera pose or depth)."""
        if T_world_from_cam is None or depth_m is None:
            return
        T_cam_from_world = T_world_from_cam.inverse()
        self._cams[name] = T_cam_from_world
        here = self._by_frame.get(name, {})
        for tr in self.tracks:
            if tr.world != world:
                continue
            proj = project_visible(self.geometry(tr.obj_id), T_cam_from_world @ tr.T_world_from_obj,
                                   np.asarray(K, float), np.asarray(depth_m, float), self.cfg)
            rec = here.get(tr.track_id)
            if rec is not None:
                iou = 0.0 if proj is None else float(box_iou(proj.box_xyxy[None], np.asarray(rec.box_xyxy)[None])[0, 0])
                self._ious[tr.track_id].append(iou)
                if proj is not None and self.cfg.reproject:
                    self._own[(tr.track_id, name)] = proj
            elif proj is not None:
                self._cands[tr.track_id].append(_Candidate(index, name, proj))

    def trusted(self, track_id: int) -> bool:
        """Whether a track's projection agrees with its detections (``consistency_iou``), its CAD model fits its depth
        (``max_fit_rel``) and it was detected in enough of the frames that show it (``min_detected``). Frames without
        camera pose or depth do not count."""
        ious = self._ious.get(track_id)
        if not ious or float(np.median(ious)) < self.cfg.consistency_iou:
            return False
        fit = self._fit.get(track_id)
        if fit is not None and fit > self.cfg.max_fit_rel:
            return False
        n = self._n[track_id]
        return n >= self.cfg.min_detected * (n + len(self._cands.get(track_id, [])))

    def _as_completed(self, r: Any, tr: WorldTrack) -> Any:
        """A trusted track's detection as reported: its CAD model (the refit may have chosen another), its world pose
        (``smooth``, or always when the model changed), and the box and mask that pose projects to in the frame
        (``reproject``; the network's box kept as ``box_detector``)."""
        changed = r.obj_id != tr.obj_id
        r = replace(r, obj_id=tr.obj_id)
        if (self.cfg.smooth or changed) and r.frame_name in self._cams:
            r = replace(r, T_cam_from_obj=self._cams[r.frame_name] @ tr.T_world_from_obj)
        p = self._own.get((r.track_id, r.frame_name))
        if p is None:  # only filled with reproject on
            return r
        return replace(r, box_xyxy=p.box_xyxy, mask=p.mask,
                       box_detector=r.box_xyxy if r.box_detector is None else r.box_detector)

    def result(self) -> tuple[list[Any], dict]:
        """The completed records (per-frame records kept and added, by frame) and a summary of the pass."""
        keep = [r for r in self.records  # track id -1: not fused (temporal mode none), nothing to count
                if not self.cfg.drop_short or r.track_id < 0 or self._n[r.track_id] >= self.cfg.min_obs]
        trusted = [tr for tr in self.tracks if self.trusted(tr.track_id)]
        keepers = {tr.track_id for tr in trusted}
        dup = {tr.track_id for tr in self.tracks if tr.duplicate_of in keepers}
        checked = {tr.track_id for tr in self.tracks if tr.track_id in self._ious}  # untrusted unless a keeper
        drop = dup | (checked - keepers) if self.cfg.drop_untrusted else dup
        keep = [r for r in keep if r.track_id not in drop]
        trusted = [tr for tr in trusted if tr.track_id not in dup]
        by_id = {tr.track_id: tr for tr in trusted}
        keep = [self._as_completed(r, by_id[r.track_id]) if r.track_id in by_id else r for r in keep]
        boxes: dict[tuple[str, int], list[np.ndarray]] = defaultdict(list)
        for r in keep:
            boxes[(r.frame_name, r.label)].append(np.asarray(r.box_xyxy, float))
        scores: dict[int, list[float]] = defaultdict(list)
        for r in self.records:
            scores[r.track_id].append(r.score)
        template = {r.track_id: r for r in self.records}
        added: Counter = Counter()
        out = list(keep)
        for tr in sorted(trusted, key=lambda t: (-self._n[t.track_id], t.track_id)):
            ref, score = template[tr.track_id], float(np.median(scores[tr.track_id]))
            for c in self._cands.get(tr.track_id, []):
                have = boxes[(c.name, tr.label)]
                if have and box_iou(c.proj.box_xyxy[None], np.array(have)).max() >= self.cfg.dedup_iou:
                    continue
                have.append(c.proj.box_xyxy)
                T = c.proj.T_cam_from_obj
                out.append(replace(ref, frame=c.frame, frame_name=c.name, obj_id=tr.obj_id, score=score,
                                   box_xyxy=c.proj.box_xyxy,
                                   T_cam_from_obj=T, T_detector=T, T_refined=T, refine_iters={}, mask=c.proj.mask,
                                   source="track", box_detector=None))
                added[ref.class_name] += 1
        out.sort(key=lambda r: (r.frame, r.source != "detector", -r.score))
        summary = {"tracks": len(self.tracks), "untrusted": len(self.tracks) - len(trusted) - len(dup),
                   "duplicates": len(dup),
                   "added": dict(added), "dropped": len(self.records) - len(keep)}
        return out, summary

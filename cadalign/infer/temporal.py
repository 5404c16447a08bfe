"""Temporal fusion of per-frame poses of static parts on video.

Three modes, chosen per frame by whether the camera pose ``T_world_from_cam`` is known (``mode="auto"``):

- ``world``: each observation is moved to the world frame; a track's estimate is a robust (Huber IRLS)
  mean of its last ``window`` observations: translations averaged, rotations by the chordal mean
  projected back to SO(3). The part is static, so this is the maximum-likelihood estimate under noise.
- ``ego``: no camera poses: the camera pose is estimated from the static parts themselves (a consensus of
  the frame's observations against the tracks' world poses, :mod:`cadalign.infer.ego`; the camera follows a
  constant-velocity model on SE(3) between frames), then fused as ``world``. The "world" is the camera frame
  of the first frame with observations.
- ``filter``: a constant-velocity filter on SE(3) per part in the camera frame (an alpha-beta filter, the
  steady-state Kalman filter of a constant-velocity model) with the left twist ``xi = (omega, v)`` per frame
  as velocity; observations beyond the gate are treated as outliers. It lags a moving camera (each part's
  velocity is learnt separately from its own few frames) and is kept for a frame ``ego`` cannot register.

Symmetric parts: every observation is first replaced by its symmetric equivalent ``T S`` closest in
rotation to the track's current estimate (the continuous case in closed form: the rotation angle about
the axis maximising ``trace``), so estimates never flip between equivalent solutions. A new track is
canonicalised towards the identity rotation of the frame it lives in, a deterministic choice.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from cadalign.infer.config import TemporalConfig
from cadalign.infer.ego import predict_camera, register_camera
from cadalign.infer.pose_math import Observation, apply_twist_camera, canonicalize, robust_mean, twist_between
from cadalign.types import Rigid3

PRESETS: dict[str, TemporalConfig] = {"none": TemporalConfig(mode="none"), "default": TemporalConfig()}


def _compatible(o: Observation, tr: _Track) -> bool:
    """May ``o`` belong to ``tr``: the same model id when both have one, else the same class."""
    return tr.obj_id == o.obj_id if o.obj_id is not None and tr.obj_id is not None else tr.label == o.label


def _gate(cfg: TemporalConfig, o: Observation) -> float:
    """Translation gate (m): ``gate_m``, narrowed to half the diameter for small parts (neighbours, e.g. a
    panel's valves 0.2 m apart, must not share a track)."""
    return min(cfg.gate_m, 0.5 * o.diameter_m) if o.diameter_m > 0 else cfg.gate_m


@dataclass(frozen=True)
class FusedPose:
    """The fused pose of one observation: its track and ``T_cam_from_obj`` (canonicalised, filtered)."""

    track_id: int
    T_cam_from_obj: Rigid3
    mode: str
    n_obs: int


@dataclass
class _Track:
    track_id: int
    label: int
    obj_id: int | None
    frame: int
    T: Rigid3  # world-from-obj (world, ego) or cam-from-obj (filter) estimate
    space: str  # "world" (given camera poses), "ego" (estimated ones) or "cam" (filter)
    obs: list[Rigid3] = field(default_factory=list)
    xi: np.ndarray = field(default_factory=lambda: np.zeros(6))
    missed: int = 0
    id_px: int = 0  # the largest mask its model was identified on (Observation.id_px)
    world: int = 0  # the world its pose is in: 0 the given camera poses', 1, 2, ... the ego worlds in turn
    retired_from: str | None = None  # the space it was in before it was retired


class TemporalFuser:
    """Tracks static parts across frames and returns fused, symmetry-consistent poses (see module doc)."""

    def __init__(self, cfg: TemporalConfig) -> None:
        self.cfg = cfg
        self.tracks: list[_Track] = []
        self._ego: list[tuple[int, Rigid3]] = []
        """The last two (frame, estimated ``T_world_from_cam``) of mode ``ego``."""
        self._world = 0
        self.cameras: dict[int, tuple[int, Rigid3]] = {}
        """Per frame fused in a world: (world, ``T_world_from_cam``), the given pose (world 0) or the ego estimate
        (world 1, 2, ...: each start of ``ego`` without tracks begins a new one)."""

    def _predict(self, tr: _Track, frame: int) -> Rigid3:
        return tr.T if tr.space != "cam" else apply_twist_camera(tr.xi * (frame - tr.frame), tr.T)

    def _space(self, T_world_from_cam: Rigid3 | None) -> str:
        if T_world_from_cam is not None and self.cfg.mode in ("auto", "world"):
            return "world"
        return "ego" if self.cfg.mode in ("auto", "ego") else "cam"

    def _predicted_view(self, frame: int, T_world_from_cam: Rigid3 | None) -> tuple[str, Rigid3 | None] | None:
        """(space, camera pose) a detection of ``frame`` is compared in before the frame is fused: the given pose,
        the ego camera's prediction, or none (filter); None when the ego camera has no prediction yet."""
        space = self._space(T_world_from_cam)
        T_wc = T_world_from_cam if space == "world" else predict_camera(self._ego, frame) if space == "ego" else None
        return None if space == "ego" and T_wc is None else (space, T_wc)

    def _register(self, frame: int, obs: list[Observation]) -> Rigid3 | None:
        """This frame's estimated ``T_world_from_cam`` (mode ``ego``); None leaves the frame to the filter.

        No ego track yet: this camera is the world. Unregistered (no observation near a known part): the
        constant-velocity prediction for up to ``max_missed`` frames, then a new world (the old tracks retire).
        A frame whose parts all have a continuous symmetry cannot fix the camera's turn about them: filter.
        """
        if all(o.symmetry.kind == "continuous" for o in obs):
            return None
        tracks = [tr for tr in self.tracks if tr.space == "ego"]
        C_pred = predict_camera(self._ego, frame)
        if not tracks:
            C = Rigid3.identity()
            self._world += 1
        else:
            cands = [[k for k, tr in enumerate(tracks) if _compatible(o, tr)] for o in obs]
            C, _ = register_camera(obs, cands, [tr.T for tr in tracks], [_gate(self.cfg, o) for o in obs],
                                   self.cfg.huber_t_m, math.radians(self.cfg.huber_r_deg), C_pred)
            if C is None:
                if C_pred is not None and frame - self._ego[-1][0] <= self.cfg.max_missed:
                    C = C_pred
                else:
                    for tr in tracks:
                        tr.retired_from, tr.space = tr.space, "retired"
                    self._ego, C = [], Rigid3.identity()
                    self._world += 1
        if C is not None:
            self._ego = [*self._ego, (frame, C)][-2:]
        return C

    def tracks_in_view(self, label: int, frame: int, T_world_from_cam: Rigid3 | None = None, min_obs: int = 3
                       ) -> list[tuple[int, Rigid3]]:
        """(model id, predicted ``T_cam_from_obj`` in this frame) of every track of class ``label`` that has a model
        id and at least ``min_obs`` observations, in the space this frame will be fused in (the given camera pose,
        the predicted ego camera, or the filter's own prediction)."""
        return [(oid, T) for _, oid, T, _ in self.track_views(label, frame, T_world_from_cam, min_obs)]

    def track_views(self, label: int, frame: int, T_world_from_cam: Rigid3 | None = None, min_obs: int = 3
                    ) -> list[tuple[int, int, Rigid3, int]]:
        """As :meth:`tracks_in_view`, with each track's id first and the mask size its model rests on last
        (``(track_id, obj_id, T_cam_from_obj, id_px)``)."""
        if self.cfg.mode == "none":
            return []
        view = self._predicted_view(frame, T_world_from_cam)
        if view is None:
            return []
        space, T_wc = view
        out = []
        for tr in self.tracks:
            if tr.space != space or tr.label != label or tr.obj_id is None or len(tr.obs) < min_obs:
                continue
            T = self._predict(tr, frame)
            out.append((tr.track_id, tr.obj_id, T_wc.inverse() @ T if T_wc is not None else T, tr.id_px))
        return out

    def retire(self, track_id: int) -> None:
        """Stop a track: it takes no more observations and is no longer in view (its model was found wrong)."""
        tr = self.tracks[track_id]
        tr.retired_from, tr.space = tr.space, "retired"

    def note_identified(self, track_id: int, id_px: int) -> None:
        """The track's model was confirmed on a mask of ``id_px`` pixels."""
        tr = self.tracks[track_id]
        tr.id_px = max(tr.id_px, int(id_px))

    def _associate(self, obs: list[Observation], frame: int, T_wc: Rigid3 | None, space: str
                   ) -> list[_Track | None]:
        pairs = []
        for i, o in enumerate(obs):
            t_o = (T_wc @ o.T_cam_from_obj).t if T_wc is not None else o.T_cam_from_obj.t
            gate = _gate(self.cfg, o)
            for k, tr in enumerate(self.tracks):
                if tr.space != space or not _compatible(o, tr):
                    continue
                d = float(np.linalg.norm(self._predict(tr, frame).t - t_o))
                if d < gate:
                    pairs.append((d, i, k))
        out: list[_Track | None] = [None] * len(obs)
        used: set[int] = set()
        for _, i, k in sorted(pairs):
            if out[i] is None and k not in used:
                out[i] = self.tracks[k]
                used.add(k)
        return out

    def update(self, frame: int, obs: list[Observation], T_world_from_cam: Rigid3 | None = None) -> list[FusedPose]:
        """Fuse one frame's observations; returns one :class:`FusedPose` per observation, in order."""
        cfg = self.cfg
        if cfg.mode == "none":
            return [FusedPose(-1, o.T_cam_from_obj, "none", 1) for o in obs]
        # a frame without a camera pose is registered on the parts (``auto``, ``ego``), else filtered
        space = self._space(T_world_from_cam)
        T_wc = T_world_from_cam if space == "world" else self._register(frame, obs) if space == "ego" else None
        if space == "ego" and T_wc is None:
            space = "cam"
        world = 0 if space == "world" else self._world
        if T_wc is not None:
            self.cameras[frame] = (world, T_wc)
        out = []
        for o, tr in zip(obs, self._associate(obs, frame, T_wc, space), strict=True):
            meas = T_wc @ o.T_cam_from_obj if T_wc is not None else o.T_cam_from_obj
            if tr is None:
                tr = _Track(len(self.tracks), o.label, o.obj_id, frame, canonicalize(meas, o.symmetry, np.eye(3)),
                            space, id_px=o.id_px, world=world)
                self.tracks.append(tr)
                tr.obs.append(tr.T)
            elif tr.space != "cam":
                tr.obs = [*tr.obs, canonicalize(meas, o.symmetry, tr.T.R)][-cfg.window:]
                tr.T = robust_mean(tr.obs, cfg.huber_t_m, math.radians(cfg.huber_r_deg))
                tr.frame = frame
            else:
                self._filter_update(tr, frame, canonicalize(meas, o.symmetry, self._predict(tr, frame).R), o)
            tr.id_px = max(tr.id_px, o.id_px)
            T_cam = T_wc.inverse() @ tr.T if tr.space != "cam" and T_wc is not None else tr.T
            out.append(FusedPose(tr.track_id, T_cam, "filter" if tr.space == "cam" else tr.space, len(tr.obs)))
        return out

    def _filter_update(self, tr: _Track, frame: int, meas: Rigid3, o: Observation) -> None:
        cfg = self.cfg
        dt = max(frame - tr.frame, 1)
        pred = self._predict(tr, frame)
        delta = twist_between(pred, meas)
        outlier = (np.linalg.norm(meas.t - pred.t) > _gate(cfg, o)
                   or np.degrees(np.linalg.norm(delta[:3])) > cfg.gate_deg)
        if outlier and tr.missed < cfg.max_missed:
            tr.missed += 1
            tr.T, tr.frame = pred, frame
            return
        if outlier:  # lost: restart from the measurement
            tr.T, tr.xi, tr.missed, tr.frame, tr.obs = meas, np.zeros(6), 0, frame, [meas]
            return
        tr.T = apply_twist_camera(cfg.alpha * delta, pred)
        tr.xi = tr.xi + cfg.beta * delta / dt
        tr.missed, tr.frame = 0, frame
        tr.obs = [*tr.obs, meas][-cfg.window:]

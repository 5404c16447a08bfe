"""Speed of the structure tracker against the detector alone, on the same frames in the same process.

``cadalign bench track`` runs, over one video's frames:
- the tracker (RGB only) started from a rough first-frame pose; frames/s of tracked frames, as CPU time of this
  process (which a busy shared machine inflates less than wall time) and as wall time (what "on 2 cores" means
  on a quiet machine), and the time of one restart (a start from the rough pose: the pan/tilt/roll search and
  its contour fits);
- the detector alone (the Mask R-CNN + pose network) on the same frames: a trained run (``--model``), or a
  network of the recipe's architecture with random weights (compute does not depend on the weights; the report
  says which).
The ratio of the two is the result; absolute times on a shared machine are noise. With ``repeats`` both are timed
several times in turn and each figure is the median over the repeats (a shared machine's other jobs slow some).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cadalign.config import resolve
from cadalign.infer.detect import TorchDetector
from cadalign.infer.track.config import TrackerConfig, TrackRunConfig
from cadalign.infer.track.edges import as_gray
from cadalign.infer.track.run import working_camera
from cadalign.infer.track.tracker import StructureTracker
from cadalign.infer.video import iter_frames
from cadalign.sim.structure import Structure
from cadalign.types import Camera, Rigid3


@dataclass(frozen=True)
class TrackSpeed:
    frames: int
    tracked: int
    track_ms: float
    """Mean CPU ms of a tracked (continued) frame."""
    restart_ms: float
    """CPU ms of the start from the rough pose."""
    detector_ms: float
    """Mean CPU ms of the detector alone on the same frames."""
    detector: str
    track_ms_wall: float = float("nan")
    """Mean wall-clock ms of a tracked frame (all the process' threads at work)."""
    detector_ms_wall: float = float("nan")
    """Mean wall-clock ms of the detector alone."""
    repeats: tuple[dict, ...] = ()
    """With several repeats, each one's times (the fields above are their medians); empty for one."""

    @property
    def ratio(self) -> float:
        """Tracker frames/s over the detector's."""
        return self.detector_ms / self.track_ms if self.track_ms > 0 else float("nan")

    def record(self) -> dict:
        tracked_on = bool(np.isfinite(self.track_ms) and self.track_ms > 0)
        return {"frames": self.frames, "tracked": self.tracked, "track_ms_cpu": self.track_ms if tracked_on else None,
                "track_frames_per_s_cpu": 1e3 / self.track_ms if tracked_on else None,
                "track_frames_per_s_wall": 1e3 / self.track_ms_wall if tracked_on else None,
                **({} if tracked_on else {"problem": "no frame was tracked on from the one before (each was lost or "
                                                     "restarted): no tracking rate; give a video the tracker follows"}),
                "restart_ms_cpu": self.restart_ms, "detector_ms_cpu": self.detector_ms,
                "detector_frames_per_s_cpu": 1e3 / self.detector_ms if self.detector_ms else None,
                "tracker_over_detector": self.ratio if tracked_on else None,
                "track_ms_wall": self.track_ms_wall if tracked_on else None, "detector_ms_wall": self.detector_ms_wall,
                "tracker_over_detector_wall": self.detector_ms_wall / self.track_ms_wall if tracked_on else None,
                "detector": self.detector,
                **({"repeats": list(self.repeats), "median_of": len(self.repeats)} if self.repeats else {}),
                "note": "CPU time of this process per frame (torch and Open3D use its threads) and wall time; same "
                        "frames, same run; wall time means something only on an otherwise idle machine"}


def time_tracker(frames: list[np.ndarray], structure: Structure, camera: Camera, init_pose: Rigid3,
                 cfg: TrackerConfig | None = None) -> tuple[float, list[float], int, list[float]]:
    """(CPU s of the start, CPU s of each continued frame, frames tracked, wall s of each continued frame)."""
    tr = StructureTracker(structure.render_meshes(), camera, cfg)
    colour = tr.cfg.edges.colour
    start, per, ok, wall = 0.0, [], 0, []
    for k, img in enumerate(frames):
        g = as_gray(img, colour)
        c0, w0 = time.process_time(), time.perf_counter()
        rgb = img[..., :3] if img.ndim == 3 else None
        s = tr.step(g, [("init_pose", init_pose)] if tr.last_pose is None else [], rgb)
        dt, dw = time.process_time() - c0, time.perf_counter() - w0
        ok += s.state == "ok"
        if k == 0:
            start = dt
        elif s.source == "track":
            per.append(dt)
            wall.append(dw)
    return start, per, ok, wall


def _detector(camera: Camera, model: Path | None, classes: tuple[str, ...],
              recipe: Path | None = None) -> tuple[TorchDetector, str]:
    """The detector the tracker is compared with, and what it is."""
    import torch  # lazy: heavy dependency (torch)

    if model is not None:
        from cadalign.models.maskrcnn.detector import load_pose_model  # lazy: pulls torch

        net, _ = load_pose_model(model)
        what = f"trained network {model}"
    else:
        from cadalign.models.maskrcnn.detector import MaskRCNNPose  # lazy: pulls torch
        from cadalign.train.pose import PRESETS, PoseTrainConfig  # lazy: pulls kornia, torch

        cfg = resolve(PoseTrainConfig, PRESETS, "fast", recipe)
        torch.manual_seed(0)
        net = MaskRCNNPose(cfg.model, list(classes)).eval()
        what = (f"the architecture of {recipe or 'the fast preset'} with random weights, no detection kept (score "
                "threshold above 1): backbone, RPN and box head only, a lower bound of a trained network's time")
    return TorchDetector(net, 0.5 if model is not None else 1.01, "cpu"), what


def time_detector(frames: list[np.ndarray], camera: Camera, det: TorchDetector) -> tuple[list[float], list[float]]:
    """CPU s and wall s per frame of the detector alone."""
    per, wall = [], []
    for img in frames:
        c0, w0 = time.process_time(), time.perf_counter()
        det.detect(img, camera.K)
        per.append(time.process_time() - c0)
        wall.append(time.perf_counter() - w0)
    return per, wall


def bench_track(source: Path, structure: Structure, camera: Camera, init_pose: Rigid3, *, model: Path | None = None,
                recipe: Path | None = None, max_frames: int = 30, cfg: TrackerConfig | None = None,
                max_width: int = TrackRunConfig().max_width, repeats: int = 1) -> TrackSpeed:
    """The tracker and the detector alone on the first ``max_frames`` frames of ``source`` (module doc); the tracker
    sees frames wider than ``max_width`` at that width, as ``infer`` gives them to it. ``repeats``: both are timed
    this many times, in turn (a fresh tracker each time); each time is the median over the repeats (the other jobs of
    a shared machine slow some repeats), and :attr:`TrackSpeed.repeats` keeps every repeat's."""
    frames = [vf.image for vf in iter_frames(source, max_frames=max_frames)]
    work = working_camera(camera, max_width)
    small = frames if work.width == camera.width else [
        cv2.resize(f, (work.width, work.height), interpolation=cv2.INTER_AREA) for f in frames]
    det, what = _detector(camera, model, structure.class_names, recipe)
    runs, ok = [], 0
    for _ in range(max(repeats, 1)):
        start, per, ok, wall = time_tracker(small, structure, work, init_pose, cfg)
        d_per, d_wall = time_detector(frames, camera, det)
        runs.append({"track_ms_cpu": _ms(per), "track_ms_wall": _ms(wall), "restart_ms_cpu": 1e3 * start,
                     "detector_ms_cpu": _ms(d_per), "detector_ms_wall": _ms(d_wall)})

    def med(key: str) -> float:
        return float(np.median([r[key] for r in runs]))

    return TrackSpeed(len(frames), ok, med("track_ms_cpu"), med("restart_ms_cpu"), med("detector_ms_cpu"), what,
                      med("track_ms_wall"), med("detector_ms_wall"), tuple(runs) if repeats > 1 else ())


def _ms(seconds: list[float]) -> float:
    """Mean milliseconds of per-frame times in seconds (NaN: none)."""
    return 1e3 * float(np.mean(seconds)) if seconds else float("nan")

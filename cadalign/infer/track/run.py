"""``infer`` with the structure tracker on disk: RGB video + CAD + intrinsics -> per-frame part poses.

Outputs in ``out_dir`` (the layout of :mod:`cadalign.infer.run`, so ``eval`` and the report read both)::

    poses.jsonl     one record per reported part and tracked frame (``source``: ``tracked``); nothing for a
                    frame while the track is lost, nor for a part whose contours find no support (missing)
    track.jsonl     one line per frame: state (ok / lost), T_cam_from_world, edge support, residual, restart
    overlay.mp4     the frames with the tracked CAD's contours (green: an image edge supports them, red: none)
                    and the state
    frames.json     the frame names processed
    timings.json    ms per frame: tracking, restarts, overlay; frames/s
    eval.json, eval.md   with ground truth (--gt): as for the detector pipeline; every section scores the
                    tracked poses
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cadalign.build_dataset import Structure
from cadalign.errors import InputError
from cadalign.formats.calibration import CameraCalibration, Undistorter
from cadalign.infer.pipeline import PoseRecord
from cadalign.infer.track.edges import EdgeLevel, EdgeTrackConfig, as_gray, with_levels
from cadalign.infer.track.tracker import StructureTracker, TrackerConfig, TrackStep
from cadalign.infer.video import iter_frames
from cadalign.io import atomic_path, prepare_stage_dir, read_json, write_json
from cadalign.types import Camera, Rigid3

log = logging.getLogger(__name__)
Progress = Callable[[Iterable, str, int | None], Iterable]


@dataclass(frozen=True)
class TrackRunConfig:
    """The tracker stage: the tracker and what is reported of each part."""

    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    min_visible_px: int = 4
    """A part is reported in a tracked frame when at least this many of its pixels are visible at the pose."""
    min_part_samples: int = 30
    """A part with at least this many contour samples is checked for support (fewer: too little to judge)."""
    min_part_support: float = 0.2
    """A checked part whose contour samples find image edges less often than this is reported missing (not
    where the CAD puts it), not placed."""
    min_part_concentration: float = 0.0
    """A checked part whose found edges lie near its outline less often than this (see
    :attr:`~cadalign.infer.track.edges.EdgeFit.instance_support`) is reported missing: near edges of texture or
    clutter where the part should be do not make it present."""
    overlay: bool = True
    """Write overlay.mp4."""
    overlay_fps: float = 5.0
    """Frames per second of overlay.mp4."""


PRESETS: dict[str, TrackRunConfig] = {
    "fast": TrackRunConfig(TrackerConfig(edges=EdgeTrackConfig(levels=(EdgeLevel(0.25, 4, 6.0, 4.0),
                                                                       EdgeLevel(0.5, 3, 3.0, 2.0))))),
    "balanced": TrackRunConfig(),
    "accurate": TrackRunConfig(TrackerConfig(edges=with_levels(EdgeTrackConfig(), iterations=6))),
}
"""``none`` is not a tracker preset; the CLI maps the detector pipeline's preset names onto these."""


def read_init_pose(path: Path) -> Rigid3:
    """``T_cam_from_world`` of the first frame from a JSON file ``{"T_cam_from_world": 4x4 nested list}``
    (metres; a navigation pose good to ~0.5 m / 10 deg serves)."""
    try:
        data = read_json(path)
        M = np.asarray(data["T_cam_from_world"], dtype=np.float64)
        if M.shape != (4, 4):
            raise ValueError(f"shape {M.shape}, expected (4, 4)")
        return Rigid3.from_matrix(M)
    except (KeyError, ValueError, TypeError) as exc:
        raise InputError(f"{path}: not an initial pose ({exc}); write {{\"T_cam_from_world\": [[r00, r01, r02, tx], "
                         f"..., [0, 0, 0, 1]]}} in metres, the structure (scene) frame in the first camera") from exc


def part_records(step: TrackStep, frame_index: int, name: str, structure: Structure, cfg: TrackRunConfig,
                 ) -> tuple[list[PoseRecord], list[str]]:
    """The records of one tracked frame's visible parts, and the names of parts found missing."""
    if step.T_cam_from_world is None or step.fit is None or step.fit.instance is None:
        return [], []
    inst = step.fit.instance
    counts = np.bincount(inst.ravel(), minlength=len(structure.objects) + 1)
    out, missing = [], []
    for i, o in enumerate(structure.objects):
        k = i + 1
        if counts[k] < cfg.min_visible_px:
            continue
        n, share, conc = step.fit.instance_support.get(k, (0, 0.0, 0.0))
        if n >= cfg.min_part_samples and (share < cfg.min_part_support or conc < cfg.min_part_concentration):
            missing.append(o.name)
            continue
        ys, xs = np.nonzero(inst == k)
        box = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], dtype=np.float64)
        T = step.T_cam_from_world @ o.T_world_from_obj
        score = float(share) if n else float(step.fit.support)
        out.append(PoseRecord(frame_index, name, o.obj_id, k, o.class_id, structure.class_names[o.class_id], score,
                              box, T, T, T, {}, inst == k, "tracked"))
    return out, missing


def _draw(image: np.ndarray, step: TrackStep) -> np.ndarray:
    import cv2

    img = image.copy()
    f = step.fit
    if step.state == "ok" and f is not None and f.uv is not None and len(f.uv):
        p = np.round(f.uv).astype(int)
        okp = (p[:, 0] >= 0) & (p[:, 0] < img.shape[1]) & (p[:, 1] >= 0) & (p[:, 1] < img.shape[0])
        sup = f.supported
        img[p[okp & sup, 1], p[okp & sup, 0]] = (60, 255, 60)
        img[p[okp & ~sup, 1], p[okp & ~sup, 0]] = (255, 60, 60)
    text = (f"ok ({step.source}) support {f.support:.2f} residual {f.residual_px:.2f} px" if step.state == "ok"
            and f is not None else "LOST: no pose reported")
    cv2.putText(img, text, (8, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255) if step.state == "ok"
                else (255, 80, 80), 1, cv2.LINE_AA)
    return img


def track_video(cfg: TrackRunConfig, source: Path, structure: Structure, camera: Camera, out_dir: Path, *,
                init_pose: Rigid3 | None = None, restart_source: Callable[[np.ndarray, str], list] | None = None,
                gt_scene: Path | None = None, max_frames: int | None = None, overwrite: bool = False,
                progress: Progress | None = None, record: dict | None = None,
                lens: CameraCalibration | None = None, topic: str | None = None) -> Path:
    """Track the structure through a video or frame folder; returns ``out_dir / "poses.jsonl"`` (module doc).

    ``init_pose``: ``T_cam_from_world`` of the first frame (rough). ``restart_source(image, name)``: restart
    hypotheses (name, ``T_cam_from_world``) for a frame without a track (e.g. from a detector); at least one of
    the two is needed. ``lens``: the calibration read from the user's file; a lens distortion in it is undone
    on every frame before tracking (``camera`` is then its pinhole part)."""
    if init_pose is None and restart_source is None:
        raise InputError("the tracker needs a start: pass --init-pose FILE (a rough first-frame pose) or --model RUN "
                         "(a trained detector)")
    out_dir = Path(out_dir)
    undistort = Undistorter.of(lens) if lens is not None else None
    rec = {"track": cfg, "source": str(source), "topic": topic, "max_frames": max_frames, "camera": camera.K.tolist(),
           "calibration": None if lens is None else lens.record(),
           "init_pose": None if init_pose is None else init_pose.matrix().tolist(), **(record or {})}
    poses_path = out_dir / "poses.jsonl"
    if prepare_stage_dir(out_dir, "infer", rec, overwrite=overwrite) and (out_dir / "timings.json").is_file():
        log.info("infer: %s is complete for this config; reusing it", poses_path)
        return poses_path
    tracker = StructureTracker(structure.render_meshes(), camera, cfg.tracker)
    records: list[PoseRecord] = []
    names: list[str] = []
    times: dict[str, list[float]] = {"track": [], "restart": [], "detector": [], "overlay": []}
    states = {"ok": 0, "lost": 0}
    writer = None
    frames = iter_frames(source, max_frames=max_frames, topic=topic)
    video_ctx = atomic_path(out_dir / "overlay.mp4") if cfg.overlay else contextlib.nullcontext(None)
    with atomic_path(poses_path) as tmp_poses, atomic_path(out_dir / "track.jsonl") as tmp_track, \
            video_ctx as tmp_video:
        with open(tmp_poses, "w", encoding="utf-8") as fh, open(tmp_track, "w", encoding="utf-8") as th:
            for vf in progress(frames, "track", max_frames) if progress else frames:
                if vf.image.shape[:2] != (camera.height, camera.width):
                    raise InputError(f"{source}: frame {vf.name} is {vf.image.shape[1]}x{vf.image.shape[0]} but the "
                                     f"calibration is {camera.width}x{camera.height}; pass the calibration of this "
                                     "video")
                image = undistort(vf.image) if undistort is not None else vf.image
                restarts = []
                if init_pose is not None and tracker.last_pose is None:  # until the track first starts
                    restarts.append(("init_pose", init_pose))
                t0 = time.perf_counter()
                if restart_source is not None and tracker.lost:
                    restarts += list(restart_source(image, vf.name))
                    times["detector"].append(time.perf_counter() - t0)
                step = tracker.step(as_gray(image), restarts)
                (times["restart"] if step.source not in ("track",) else times["track"]).append(step.seconds)
                states[step.state] += 1
                recs, missing = part_records(step, vf.index, vf.name, structure, cfg)
                for r in recs:
                    fh.write(json.dumps(r.to_json()) + "\n")
                records.extend(recs)
                th.write(json.dumps(_step_json(step, vf.name, missing, structure)) + "\n")
                if cfg.overlay:
                    t0 = time.perf_counter()
                    writer = writer or _video_writer(tmp_video, cfg.overlay_fps)
                    writer.append_data(_draw(image, step))
                    times["overlay"].append(time.perf_counter() - t0)
                names.append(vf.name)
        if writer is not None:
            writer.close()
    write_json(out_dir / "frames.json", names)
    write_json(out_dir / "timings.json", _timings(times, len(names), states))
    log.info("track: %d frames, %d tracked, %d lost, %d poses -> %s", len(names), states["ok"], states["lost"],
             len(records), poses_path)
    if gt_scene is not None:
        from cadalign.infer.run import evaluate_run

        evaluate_run(records, names, gt_scene, out_dir)
    return poses_path


def _step_json(step: TrackStep, name: str, missing: list[str], structure: Structure) -> dict:
    f = step.fit
    parts = {} if f is None else {structure.objects[k - 1].name: [n, round(share, 4), round(conc, 4)]
                                  for k, (n, share, conc) in sorted(f.instance_support.items()) if k > 0}
    return {"frame": step.index, "frame_name": name, "state": step.state, "source": step.source or None,
            "T_cam_from_world": None if step.T_cam_from_world is None else step.T_cam_from_world.matrix().tolist(),
            "support": None if f is None else round(float(f.support), 4),
            "residual_px": None if f is None or not np.isfinite(f.residual_px) else round(float(f.residual_px), 4),
            "contour_samples": None if f is None else int(f.samples), "missing_parts": missing,
            "part_support": parts,
            "restarts_tried": int(step.restarts_tried), "ms": round(1e3 * step.seconds, 2)}


def _timings(times: dict[str, list[float]], n: int, states: dict[str, int]) -> dict:
    def ms(v: list[float]) -> dict:
        return {"frames": len(v), "mean_ms": 1e3 * float(np.mean(v)) if v else None,
                "median_ms": 1e3 * float(np.median(v)) if v else None}

    total = sum(sum(v) for k, v in times.items() if k != "overlay")
    return {"frames": n, "tracked": states["ok"], "lost": states["lost"],
            "per_stage": {k: ms(v) for k, v in times.items()},
            "frames_per_s": n / total if total > 0 else None,
            "note": "track: frames continued from the last pose; restart: frames started from a hypothesis "
                    "(init pose, detector) or tried while lost; wall clock; overlay apart"}


def _video_writer(path: Path, fps: float):  # -> imageio writer
    from cadalign.infer.run import _video_writer as writer

    return writer(path, fps)

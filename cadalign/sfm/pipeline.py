"""``run``: video, frames folder or ROS bag image topic -> COLMAP model, cameras.json, SfM depth and a report.

Output layout (``OUT``)::

    OUT/images/<name>            the frames SfM used (pre-processed), names as in the input
    OUT/masks/<name>.png         COLMAP feature masks (only with frames.mask / frames.mask_rects)
    OUT/frames.json              every candidate frame: kept or why not (blurred, near-duplicate); the lens
                                 distortion undone (``undistorted``) when the calibration has one; a bag's
                                 frames carry their header stamp (stamp_ns), and "topic" names the topic
    OUT/database.db              COLMAP database: features and verified matches
    OUT/sparse/0/                the largest model, COLMAP binary (cameras.bin, images.bin, points3D.bin …)
    OUT/cameras.json             per registered frame K, size, R/t_cam_from_world (SfM units)
    OUT/trajectory.tum           the same poses in TUM format (camera-in-world, for evo; :mod:`cadalign.formats.tum`)
    OUT/depth/<stem>.npy         float32 semi-dense depth per registered frame, SfM units, 0 = invalid
    OUT/trajectory.png           top-down camera trajectory (plane of the cameras) with the sparse points
    OUT/sfm_report.json          frames in / registered, points, errors, unregistered frames, seconds per step,
                                 COLMAP's warnings/errors counted (``colmap_log``; its log is shown only at debug)
    OUT/steps/<step>.json        marker of each finished step (frames, features, matches, mapping, refine, export)
    OUT/cadalign_stage.json      resolved config, input identity and version

Steps run in order; a step whose marker exists is reused, and once one step runs every later
step runs again. A different config or input in ``OUT`` is refused unless ``overwrite``.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.errors import ConfigError, InputError
from cadalign.formats.bag import bag_root, is_bag
from cadalign.formats.calibration import Undistorter
from cadalign.formats.tum import TUM_NAME, write_cameras_tum
from cadalign.io import MANIFEST_NAME, atomic_path, fingerprint, prepare_stage_dir, read_json, write_json
from cadalign.sfm import colmap
from cadalign.sfm.colmap_log import colmap_log, summed
from cadalign.sfm.config import SfMConfig
from cadalign.sfm.depth import sparse_depth
from cadalign.sfm.frames import IMAGE_SUFFIXES, extract_frames, is_video
from cadalign.sfm.layout import REPORT_NAME, Layout
from cadalign.sfm.mapping import map_frames, num_verified, write_model
from cadalign.sfm.refine import refine
from cadalign.sfm.report import (
    cameras_json,
    model_stats,
    plot_trajectory,
    registered_images,
    topdown_frame,
)
from cadalign.types import Progress

log = logging.getLogger(__name__)
STEPS = ("frames", "features", "matches", "mapping", "refine", "export")
_OUTPUTS = ("images", "masks", "frames.json", "database.db", "database.db-shm", "database.db-wal", "sparse",
            "database.pre_loop.db", "database.kept.db",
            "mapping_tmp", "cameras.json", TUM_NAME, "depth", "trajectory.png", "trajectory_vs_gt.png", REPORT_NAME,
            "steps", MANIFEST_NAME)


def source_identity(source: Path, topic: str | None = None) -> dict[str, Any]:
    """What identifies an input for resuming: the resolved path plus names and sizes of its files (and a bag's
    topic, only when one is named, so the identity of videos and folders is as before bags)."""
    source = Path(source)
    root = bag_root(source)
    if root is not None:
        files = [root] if root.is_file() else sorted(p for p in root.iterdir() if p.is_file())
        ident = {"path": str(root.resolve()), "files": fingerprint([[p.name, p.stat().st_size] for p in files]),
                 "count": len(files)}
        return {**ident, "topic": topic} if topic is not None else ident
    if source.is_dir():
        files = sorted(p for p in source.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
        listing = [[p.name, p.stat().st_size] for p in files]
    else:
        listing = [[source.name, source.stat().st_size]]
    return {"path": str(source.resolve()), "files": fingerprint(listing), "count": len(listing)}


def clear_outputs(out_dir: Path) -> None:
    """Delete what a previous SfM run wrote in ``out_dir`` (and nothing else)."""
    for name in _OUTPUTS:
        p = Path(out_dir) / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()


def run(
    cfg: SfMConfig, source: Path, out_dir: Path, *, overwrite: bool = False, progress: Progress | None = None,
    topic: str | None = None,
) -> Path:
    """Structure from motion on a video, frames folder or ROS bag; returns ``out_dir`` (layout in the module doc).

    ``topic`` is a ROS bag's image topic (None: the bag's only image topic; must be None for other inputs).

    Raises:
        InputError: missing/unreadable input, or too few usable frames or features (naming the frames).
        DegenerateGeometryError: no model could be started from the matches.
        ConfigError: ``out_dir`` holds results of another config or input and ``overwrite`` is False.
    """
    source, out_dir = Path(source), Path(out_dir)
    if not source.exists():
        raise InputError(f"input not found: {source}; pass a video file, a ROS bag or a folder of frames")
    if not (source.is_dir() or is_video(source) or is_bag(source)):
        raise InputError(f"{source} is neither a video, a ROS bag (.bag, or a ROS 2 bag folder) nor a folder of "
                         "images")
    if overwrite and out_dir.exists():
        clear_outputs(out_dir)
    config = {"sfm": cfg, "source": source_identity(source, topic)}
    prepare_stage_dir(out_dir, "sfm", config)
    lay = Layout(out_dir)
    steps: dict[str, Callable[[], dict[str, Any]]] = {
        "frames": lambda: _step_frames(cfg, source, lay, progress, topic),
        "features": lambda: _step_features(cfg, lay, progress),
        "matches": lambda: _step_matches(cfg, lay),
        "mapping": lambda: _step_mapping(cfg, lay, progress),
        "refine": lambda: _step_refine(cfg, lay),
        "export": lambda: _step_export(cfg, source, lay, progress),
    }
    rerun = False
    for i, name in enumerate(STEPS):
        if not rerun and lay.marker(name).is_file():
            log.info("sfm step '%s': reusing finished work in %s", name, out_dir)
            continue
        if not rerun:
            for later in STEPS[i:]:
                lay.marker(later).unlink(missing_ok=True)
            rerun = True
        log.info("sfm step '%s'", name)
        t0 = time.perf_counter()
        with colmap_log() as colmap_said:
            info = steps[name]()
        write_json(lay.marker(name), {"step": name, "seconds": time.perf_counter() - t0, **info,
                                      "colmap_log": colmap_said.to_json()})
    _finish_report(lay, keep_gt=not rerun)
    return out_dir


def undistorter(cfg: SfMConfig) -> Undistorter:
    """The undistortion of ``cfg.camera``'s known lens distortion (inactive without one).

    Raises:
        ConfigError: a distortion without known intrinsics (the pinhole camera it undistorts to).
    """
    cam = cfg.camera
    if cam.distortion_model != "none" and any(cam.distortion) and cam.intrinsics is None:
        raise ConfigError("camera.distortion is set but camera.intrinsics is not: undistortion keeps the calibrated "
                          "K, so pass both (e.g. --calib with the lens calibration)")
    fx, fy, cx, cy = cam.intrinsics or (1.0, 1.0, 0.0, 0.0)
    return Undistorter(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), cam.distortion_model, cam.distortion)


def _kept_names(lay: Layout) -> list[str]:
    return [f["name"] for f in read_json(lay.root / "frames.json")["frames"] if f["kept"]]


def _step_frames(cfg: SfMConfig, source: Path, lay: Layout, progress: Progress | None,
                 topic: str | None) -> dict[str, Any]:
    for d in (lay.images, lay.masks):
        if d.exists():
            shutil.rmtree(d)
    undistort = undistorter(cfg)
    decisions = extract_frames(source, cfg.frames, lay.images, lay.masks, progress,
                               undistort=undistort if undistort.active else None, topic=topic)
    record: dict[str, Any] = {"source": str(source)}
    if is_bag(source):
        record["topic"] = decisions[0].source.rpartition("#")[0]
    write_json(lay.root / "frames.json", {**record, "frames": [dataclasses.asdict(d) for d in decisions],
                                          "undistorted": undistort.record() if undistort.active else None})
    return {"candidates": len(decisions), "kept": sum(d.kept for d in decisions)}


def _masks_dir(lay: Layout) -> Path | None:
    return lay.masks if lay.masks.is_dir() else None


def _step_features(cfg: SfMConfig, lay: Layout, progress: Progress | None) -> dict[str, Any]:
    names = _kept_names(lay)
    first = next(f for f in read_json(lay.root / "frames.json")["frames"] if f["kept"])
    exif = Path(first["source"]) if Path(first["source"]).suffix.lower() in (".jpg", ".jpeg", ".tif", ".tiff") else None
    counts = colmap.extract_features(cfg, lay.database, lay.images, names, _masks_dir(lay), progress, exif)
    return {"features": counts}


def _step_matches(cfg: SfMConfig, lay: Layout) -> dict[str, Any]:
    colmap.match(cfg, lay.database)
    return {"pairs_verified": num_verified(cfg, lay.database)}


def _step_mapping(cfg: SfMConfig, lay: Layout, progress: Progress | None) -> dict[str, Any]:
    return map_frames(cfg, lay, _kept_names(lay), progress)


def _step_refine(cfg: SfMConfig, lay: Layout) -> dict[str, Any]:
    import pycolmap  # lazy: heavy dependency (pycolmap)

    rec = pycolmap.Reconstruction(str(lay.model))
    info = refine(rec, cfg)
    write_model(rec, lay.model)
    return info


def _step_export(cfg: SfMConfig, source: Path, lay: Layout, progress: Progress | None) -> dict[str, Any]:
    import pycolmap  # lazy: heavy dependency (pycolmap)

    rec = pycolmap.Reconstruction(str(lay.model))
    cams = cameras_json(rec)
    write_json(lay.root / "cameras.json", cams)
    write_cameras_tum(cams, lay.root / TUM_NAME)
    coverage = []
    if cfg.depth.enabled:
        images = registered_images(rec)
        for im in progress(images, "depth", len(images)) if progress else images:
            depth = sparse_depth(rec, im.image_id, cfg.depth.splat_radius_px, cfg.depth.min_track_length)
            coverage.append(float(np.mean(depth > 0)))
            with atomic_path(lay.depth / f"{Path(im.name).stem}.npy") as tmp:
                np.save(tmp, depth)
    _plot(rec, lay.root / "trajectory.png")
    return {
        "stats": model_stats(rec),
        "camera": cams["camera"],
        "depth": {
            "written": cfg.depth.enabled,
            "format": "npy float32 (H, W), z in the camera frame",
            "units": "sfm",
            "invalid": 0.0,
            "mean_coverage": float(np.mean(coverage)) if coverage else 0.0,
        },
    }


def _plot(rec: Any, path: Path) -> None:
    images = registered_images(rec)
    C = np.array([im.projection_center() for im in images])
    R = topdown_frame(C)
    pts = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    mu = C.mean(0)
    plot_trajectory(path, ((C - mu) @ R.T)[:, :2], points_xy=((pts - mu) @ R.T)[:, :2] if len(pts) else None,
                    title=f"SfM trajectory, {len(images)} frames (plane of the cameras)")


def _finish_report(lay: Layout, keep_gt: bool) -> None:
    """sfm_report.json from the step markers (so a resumed run reports the original timings).

    A ground-truth section written by :mod:`cadalign.evaluate.sfm` is kept when nothing was recomputed.
    """
    marks = {s: read_json(lay.marker(s)) for s in STEPS}
    frames = read_json(lay.root / "frames.json")
    rejected: dict[str, list[str]] = {}
    for f in frames["frames"]:
        if not f["kept"]:
            rejected.setdefault(f["reason"], []).append(f["name"])
    n_in = marks["frames"]["kept"]
    stats = marks["export"]["stats"]
    old = read_json(lay.report) if lay.report.is_file() else {}
    report = {
        "source": frames["source"],
        "frame_candidates": marks["frames"]["candidates"],
        "frames_in": n_in,
        "frames_rejected": rejected,
        "registered": stats["registered"],
        "registration_rate": stats["registered"] / n_in if n_in else 0.0,
        **{k: v for k, v in stats.items() if k != "registered"},
        "units": "sfm",
        "camera": marks["export"]["camera"],
        "models": [{k: v for k, v in m.items() if k != "frames"} for m in marks["mapping"]["models"]],
        "other_models_frames": [m["frames"] for m in marks["mapping"]["models"][1:]],
        "unregistered": marks["mapping"]["unregistered"],
        "features_per_frame_median": float(np.median(list(marks["features"]["features"].values()) or [0])),
        "pairs_verified": marks["matches"]["pairs_verified"],
        "mapper": marks["mapping"]["mapper"],
        "loop_pairs_verified": marks["mapping"]["loop_pairs_verified"],
        "consistency": marks["mapping"].get("consistency"),
        "mapping_attempts": marks["mapping"].get("attempts", []),
        "repair": marks["mapping"].get("repair"),
        "first_pass_repair": marks["mapping"].get("first_pass_repair"),
        "segments": {k: marks["mapping"][k] for k in ("segments", "seams") if k in marks["mapping"]} or None,
        "refinement": {k: marks["refine"][k] for k in ("rounds", "before", "after")},
        "depth": marks["export"]["depth"],
        "seconds": {s: marks[s]["seconds"] for s in STEPS},
        "seconds_total": float(sum(marks[s]["seconds"] for s in STEPS)),
        "colmap_log": summed([marks[s].get("colmap_log", {}) for s in STEPS]),
        "undistorted": frames.get("undistorted"),
    }
    if keep_gt and "gt" in old:
        report["gt"] = old["gt"]
    write_json(lay.report, report)

"""``run``: video or frames folder -> COLMAP model, cameras.json, SfM depth and a report.

Output layout (``OUT``)::

    OUT/images/<name>            the frames SfM used (pre-processed), names as in the input
    OUT/masks/<name>.png         COLMAP feature masks (only with frames.mask / frames.mask_rects)
    OUT/frames.json              every candidate frame: kept or why not (blurred, near-duplicate)
    OUT/database.db              COLMAP database: features and verified matches
    OUT/sparse/0/                the largest model, COLMAP binary (cameras.bin, images.bin, points3D.bin …)
    OUT/cameras.json             per registered frame K, size, R/t_cam_from_world (SfM units)
    OUT/depth/<stem>.npy         float32 semi-dense depth per registered frame, SfM units, 0 = invalid
    OUT/trajectory.png           top-down camera trajectory (plane of the cameras) with the sparse points
    OUT/sfm_report.json          frames in / registered, points, errors, unregistered frames, seconds per step
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

from cadalign.errors import InputError
from cadalign.io import MANIFEST_NAME, atomic_path, fingerprint, prepare_stage_dir, read_json, write_json
from cadalign.sfm import colmap
from cadalign.sfm.config import SfMConfig
from cadalign.sfm.consistency import keep_largest_piece, sequence_consistency
from cadalign.sfm.depth import sparse_depth
from cadalign.sfm.frames import IMAGE_SUFFIXES, Progress, extract_frames, is_video
from cadalign.sfm.refine import model_loop_pairs, refine
from cadalign.sfm.report import (
    cameras_json,
    model_stats,
    plot_trajectory,
    registered_images,
    topdown_frame,
)

log = logging.getLogger(__name__)
STEPS = ("frames", "features", "matches", "mapping", "refine", "export")
REPORT_NAME = "sfm_report.json"
_OUTPUTS = ("images", "masks", "frames.json", "database.db", "database.db-shm", "database.db-wal", "sparse",
            "database.pre_loop.db", "database.kept.db",
            "mapping_tmp", "cameras.json", "depth", "trajectory.png", "trajectory_vs_gt.png", REPORT_NAME, "steps",
            MANIFEST_NAME)


@dataclasses.dataclass(frozen=True)
class Layout:
    """Paths of one SfM output folder."""

    root: Path

    @property
    def images(self) -> Path:
        return self.root / "images"

    @property
    def masks(self) -> Path:
        return self.root / "masks"

    @property
    def database(self) -> Path:
        return self.root / "database.db"

    @property
    def model(self) -> Path:
        return self.root / "sparse" / "0"

    @property
    def depth(self) -> Path:
        return self.root / "depth"

    @property
    def report(self) -> Path:
        return self.root / REPORT_NAME

    def marker(self, step: str) -> Path:
        return self.root / "steps" / f"{step}.json"


def source_identity(source: Path) -> dict[str, Any]:
    """What identifies an input for resuming: the resolved path plus names and sizes of its files."""
    source = Path(source)
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
    cfg: SfMConfig, source: Path, out_dir: Path, *, overwrite: bool = False, progress: Progress | None = None
) -> Path:
    """Structure from motion on a video or frames folder; returns ``out_dir`` (layout in the module doc).

    Raises:
        InputError: missing/unreadable input, or too few usable frames or features (naming the frames).
        DegenerateGeometryError: no model could be started from the matches.
        ConfigError: ``out_dir`` holds results of another config or input and ``overwrite`` is False.
    """
    source, out_dir = Path(source), Path(out_dir)
    if not source.exists():
        raise InputError(f"input not found: {source}; pass a video file or a folder of frames")
    if not (source.is_dir() or is_video(source)):
        raise InputError(f"{source} is neither a video nor a folder of images")
    if overwrite and out_dir.exists():
        clear_outputs(out_dir)
    config = {"sfm": cfg, "source": source_identity(source)}
    prepare_stage_dir(out_dir, "sfm", config)
    lay = Layout(out_dir)
    steps: dict[str, Callable[[], dict[str, Any]]] = {
        "frames": lambda: _step_frames(cfg, source, lay, progress),
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
        info = steps[name]()
        write_json(lay.marker(name), {"step": name, "seconds": time.perf_counter() - t0, **info})
    _finish_report(lay, keep_gt=not rerun)
    return out_dir


def _kept_names(lay: Layout) -> list[str]:
    return [f["name"] for f in read_json(lay.root / "frames.json")["frames"] if f["kept"]]


def _step_frames(cfg: SfMConfig, source: Path, lay: Layout, progress: Progress | None) -> dict[str, Any]:
    for d in (lay.images, lay.masks):
        if d.exists():
            shutil.rmtree(d)
    decisions = extract_frames(source, cfg.frames, lay.images, lay.masks, progress)
    write_json(lay.root / "frames.json", {"source": str(source), "frames": [dataclasses.asdict(d) for d in decisions]})
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
    return {"pairs_verified": _num_verified(cfg, lay.database)}


def _step_mapping(cfg: SfMConfig, lay: Layout, progress: Progress | None) -> dict[str, Any]:
    """Map as one model or, for long surveys, in merged segments (``mapper.segment_frames``)."""
    names = _kept_names(lay)
    work = lay.root / "mapping_tmp"
    mp = cfg.mapper
    if not mp.segment_frames or len(names) <= mp.segment_frames:
        model, info = _map_with_attempts(cfg, lay, names, work, progress)
        _write_model(model, lay.model)
        return info
    from cadalign.sfm import segments

    def map_one(sub: list[str], k: int) -> tuple[Any, dict[str, Any]]:
        return _map_with_attempts(cfg, lay, sub, work / f"segment_{k:03d}", progress)

    def merge(models: list[Any]) -> tuple[Any, list[dict[str, Any]]]:
        return segments.merge_models(models, lay.database, lay.images, work / "merged",
                                     colmap.incremental_options(cfg, names))

    merged, info = segments.map_in_segments(names, mp.segment_frames, mp.segment_overlap, map_one, merge)
    cons = sequence_consistency(merged, lay.database, names, max_px=mp.break_px, max_ratio=mp.break_ratio,
                                min_matches=mp.break_min_matches)
    _write_model(merged, lay.model)
    shutil.rmtree(work, ignore_errors=True)
    reasons = colmap.unregistered_reasons(cfg, lay.database, names, [merged])
    return {"mapper": "segments", "consistency": cons.to_dict(), **info, "unregistered": reasons,
            "loop_pairs_verified": sum(seg["loop_pairs_verified"] for seg in info["segments"]),
            "models": [{**model_stats(merged), "kept": True, "frames": [im.name for im in registered_images(merged)]}]}


def _map_with_attempts(cfg: SfMConfig, lay: Layout, names: list[str], work: Path,
                       progress: Progress | None) -> tuple[Any, dict[str, Any]]:
    """Map ``names`` (with loop closure), check the model's consistency, and retry with the next seed while
    it has breaks; each attempt starts from the matches as they were before any loop closure. Returns the
    kept model and what was done."""
    pristine, kept_db = lay.root / "database.pre_loop.db", lay.root / "database.kept.db"
    shutil.copyfile(lay.database, pristine)
    best: tuple[tuple[int, int], list[Any], dict[str, Any]] | None = None
    attempts = []
    for a in range(cfg.mapper.attempts):
        if a:
            shutil.copyfile(pristine, lay.database)
        acfg = dataclasses.replace(cfg, seed=cfg.seed + a)
        models, info = _map_once(acfg, lay, names, work, progress)
        mp = cfg.mapper
        cons = sequence_consistency(models[0], lay.database, names, max_px=mp.break_px, max_ratio=mp.break_ratio,
                                    min_matches=mp.break_min_matches)
        attempts.append({"seed": acfg.seed, "registered": models[0].num_reg_images(), **cons.to_dict()})
        key = (len(cons.breaks), -models[0].num_reg_images())
        if best is None or key < best[0]:
            best = (key, models, {**info, "consistency": cons.to_dict()})
            shutil.copyfile(lay.database, kept_db)
        if cons.ok:
            break
        log.warning("SfM attempt %d (seed %d): model breaks between %s; %s", a + 1, acfg.seed,
                    ", ".join(f"{b.frame_a}/{b.frame_b} ({b.median_px:.1f} px)" for b in cons.breaks),
                    "trying the next seed" if a + 1 < cfg.mapper.attempts else "no attempts left")
    assert best is not None
    _, models, info = best
    shutil.move(kept_db, lay.database)
    pristine.unlink()
    info["attempts"] = attempts
    dropped: dict[str, str] = {}
    if best[0][0]:
        log.warning("the kept SfM model still has %d consistency break(s): its poses are not reliable "
                    "across them (see sfm_report.json 'consistency')", best[0][0])
        if cfg.mapper.on_break == "largest_piece":
            cons = sequence_consistency(models[0], lay.database, names, max_px=cfg.mapper.break_px,
                                        max_ratio=cfg.mapper.break_ratio, min_matches=cfg.mapper.break_min_matches)
            dropped = keep_largest_piece(models[0], names, cons)
            log.warning("kept the largest consistent piece: %d frames dropped", len(dropped))
    shutil.rmtree(work, ignore_errors=True)
    if len(models) > 1:
        log.warning("SfM produced %d disconnected models (%s frames); keeping the largest",
                    len(models), ", ".join(str(r.num_reg_images()) for r in models))
    reasons = {**colmap.unregistered_reasons(cfg, lay.database, names, models), **dropped}
    if reasons:
        log.warning("%d of %d frames are not in the kept model", len(reasons), len(names))
    info["models"] = [{**model_stats(r), "kept": k == 0, "frames": [im.name for im in registered_images(r)]}
                      for k, r in enumerate(models)]
    info["unregistered"] = reasons
    return models[0], info


def _map_once(cfg: SfMConfig, lay: Layout, names: list[str], work: Path,
              progress: Progress | None) -> tuple[list[Any], dict[str, Any]]:
    """One mapping pass plus pose-guided loop closure; returns the models (largest first) and what it did."""
    t0 = time.perf_counter()
    result = colmap.reconstruct(cfg, lay.database, lay.images, work, names, progress)
    models = result.models
    info: dict[str, Any] = {"seconds_first_pass": time.perf_counter() - t0, "mapper": result.mapper,
                            "loop_pairs": 0, "loop_pairs_verified": 0}
    if cfg.matching.loop_closure and cfg.matching.pairing == "sequential":
        t0 = time.perf_counter()
        pairs = model_loop_pairs(models[0], names, cfg)
        if pairs:
            before = _num_verified(cfg, lay.database)
            colmap.match_pairs(cfg, lay.database, pairs, work / "loop_pairs.txt")
            info["loop_pairs"] = len(pairs)
            info["loop_pairs_verified"] = _num_verified(cfg, lay.database) - before
            log.info("loop closure: %d candidate pairs, %d verified", len(pairs), info["loop_pairs_verified"])
            if info["loop_pairs_verified"]:  # map again with the mapper that worked
                again = dataclasses.replace(cfg, mapper=dataclasses.replace(cfg.mapper, kind=result.mapper))
                models = colmap.reconstruct(again, lay.database, lay.images, work, names, progress).models
        info["seconds_loop_closure"] = time.perf_counter() - t0
    return models, info


def _num_verified(cfg: SfMConfig, database: Path) -> int:
    import pycolmap

    with pycolmap.Database.open(database) as db:
        _, geoms = db.read_two_view_geometries()
    return sum(len(g.inlier_matches) >= cfg.matching.min_num_inliers for g in geoms)


def _write_model(rec: Any, path: Path) -> None:
    """Write a model as COLMAP binary into ``path`` by swapping a finished temporary folder in."""
    tmp = path.parent / f".{path.name}.tmp"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    rec.write_binary(str(tmp))
    if path.exists():
        shutil.rmtree(path)
    tmp.rename(path)


def _step_refine(cfg: SfMConfig, lay: Layout) -> dict[str, Any]:
    import pycolmap

    rec = pycolmap.Reconstruction(str(lay.model))
    info = refine(rec, cfg)
    _write_model(rec, lay.model)
    return info


def _step_export(cfg: SfMConfig, source: Path, lay: Layout, progress: Progress | None) -> dict[str, Any]:
    import pycolmap

    rec = pycolmap.Reconstruction(str(lay.model))
    cams = cameras_json(rec)
    write_json(lay.root / "cameras.json", cams)
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

    A ground-truth section written by :mod:`cadalign.eval.sfm_metrics` is kept when nothing was recomputed.
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
        "segments": {k: marks["mapping"][k] for k in ("segments", "seams") if k in marks["mapping"]} or None,
        "refinement": {k: marks["refine"][k] for k in ("rounds", "before", "after")},
        "depth": marks["export"]["depth"],
        "seconds": {s: marks[s]["seconds"] for s in STEPS},
        "seconds_total": float(sum(marks[s]["seconds"] for s in STEPS)),
    }
    if keep_gt and "gt" in old:
        report["gt"] = old["gt"]
    write_json(lay.report, report)

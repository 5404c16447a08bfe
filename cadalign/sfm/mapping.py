"""The mapping step of :func:`cadalign.sfm.pipeline.run`: mapping attempts with loop closure and the
consistency check, segmented mapping of long surveys, and writing the kept model.

Each attempt maps with the next seed while the model has consistency breaks (:mod:`cadalign.sfm.consistency`)
and starts from the matches as they were before any loop closure; the first sound model, else the one with the
fewest breaks, is kept. When every attempt broke, the breaks are repaired by re-mapping a window round each on
its own (:mod:`cadalign.sfm.repair`), else the model is cut to its largest consistent piece (``mapper.on_break``).
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import time
from pathlib import Path
from typing import Any

from cadalign.sfm import colmap, repair, segments
from cadalign.sfm.colmap_log import stderr_captured
from cadalign.sfm.config import SfMConfig
from cadalign.sfm.consistency import Consistency, keep_largest_piece, sequence_consistency
from cadalign.sfm.layout import Layout
from cadalign.sfm.loop_merge import merge_loop_tracks
from cadalign.sfm.refine import model_loop_pairs
from cadalign.sfm.report import model_stats, registered_images
from cadalign.types import Progress

log = logging.getLogger(__name__)


def map_frames(cfg: SfMConfig, lay: Layout, names: list[str], progress: Progress | None) -> dict[str, Any]:
    """Map ``names`` as one model or, for long surveys, in merged segments (``mapper.segment_frames``); the kept
    model is written to ``lay.model``. Returns what was done (the mapping step's marker)."""
    work = lay.root / "mapping_tmp"
    mp = cfg.mapper
    if not mp.segment_frames or len(names) <= mp.segment_frames:
        model, info = _map_with_attempts(cfg, lay, names, work, progress)
        write_model(model, lay.model)
        return info

    def map_one(sub: list[str], k: int) -> tuple[Any, dict[str, Any]]:
        return _map_with_attempts(cfg, lay, sub, work / f"segment_{k:03d}", progress)

    def merge(models: list[Any]) -> tuple[Any, list[dict[str, Any]]]:
        return segments.merge_models(models, lay.database, lay.images, work / "merged",
                                     colmap.incremental_options(cfg, names))

    merged, info = segments.map_in_segments(names, mp.segment_frames, mp.segment_overlap, map_one, merge)
    cons = _consistency(cfg, lay, merged, names)
    write_model(merged, lay.model)
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
    # loop closure adds matches to the database: each attempt starts from the matches before it, and the kept
    # attempt's database is put back at the end (a repair window maps without loop closure: no copies)
    loops = cfg.matching.loop_closure and cfg.matching.pairing == "sequential"
    pristine, kept_db = lay.root / "database.pre_loop.db", lay.root / "database.kept.db"
    if loops:
        shutil.copyfile(lay.database, pristine)
    best: tuple[tuple[int, int], list[Any], dict[str, Any]] | None = None
    attempts = []
    for a in range(cfg.mapper.attempts):
        if a and loops:
            shutil.copyfile(pristine, lay.database)
        acfg = dataclasses.replace(cfg, seed=cfg.seed + a)
        models, info = _map_once(acfg, lay, names, work, progress)
        cons = _consistency(cfg, lay, models[0], names)
        attempts.append({"seed": acfg.seed, "registered": models[0].num_reg_images(), **cons.to_dict()})
        key = (len(cons.breaks), -models[0].num_reg_images())
        if best is None or key < best[0]:
            best = (key, models, {**info, "consistency": cons.to_dict()})
            if loops:
                shutil.copyfile(lay.database, kept_db)
        if cons.ok:
            break
        log.warning("SfM attempt %d (seed %d): model breaks between %s; %s", a + 1, acfg.seed,
                    ", ".join(f"{b.frame_a}/{b.frame_b} ({b.median_px:.1f} px)" for b in cons.breaks),
                    "trying the next seed" if a + 1 < cfg.mapper.attempts else "no attempts left")
    assert best is not None
    _, models, info = best
    if loops:
        shutil.move(kept_db, lay.database)
        pristine.unlink()
    info["attempts"] = attempts
    dropped: dict[str, str] = {}
    if best[0][0]:
        log.warning("the kept SfM model still has %d consistency break(s): its poses are not reliable "
                    "across them (see sfm_report.json 'consistency')", best[0][0])
        cons = _consistency(cfg, lay, models[0], names)
        repaired = None
        if cfg.mapper.on_break == "repair":
            repaired, info["repair"] = _repair(cfg, lay, models[0], names, cons, work, progress)
            if repaired is not None:
                models = [repaired, *models[1:]]
                info["consistency"] = info["repair"]["consistency"]
                log.warning("repaired the break(s) by re-mapping %s on their own",
                            ", ".join("..".join(w["frames"]) for w in info["repair"]["windows"]))
            else:
                log.warning("could not repair the break(s): %s", info["repair"]["why_not"])
        if repaired is None and cfg.mapper.on_break in ("repair", "largest_piece"):
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


def _consistency(cfg: SfMConfig, lay: Layout, rec: Any, names: list[str]) -> Consistency:
    mp = cfg.mapper
    return sequence_consistency(rec, lay.database, names, max_px=mp.break_px, max_ratio=mp.break_ratio,
                                min_matches=mp.break_min_matches)


def _repair(cfg: SfMConfig, lay: Layout, rec: Any, names: list[str], cons: Consistency, work: Path,
            progress: Progress | None) -> tuple[Any | None, dict[str, Any]]:
    """:func:`cadalign.sfm.repair.repair_breaks` of ``rec``: each window is mapped like a model of its own
    (the same seeds and retries; no loop closure, no nested repair)."""

    wcfg = dataclasses.replace(cfg, matching=dataclasses.replace(cfg.matching, loop_closure=False),
                               mapper=dataclasses.replace(cfg.mapper, on_break="keep_all"))

    def map_window(sub: list[str], k: int) -> tuple[Any, Consistency]:
        model, _ = _map_with_attempts(wcfg, lay, sub, work / f"repair_{k:03d}", progress)
        repair.adopt_camera(model, rec, cfg.num_threads)
        return model, _consistency(cfg, lay, model, sub)

    def merge(models: list[Any], adds: list[set[str] | None]) -> tuple[Any, list[dict[str, Any]]]:
        return segments.merge_models(models, lay.database, lay.images, work / "repair_merged",
                                     colmap.incremental_options(cfg, names), adds)

    return repair.repair_breaks(rec, names, cons, cfg.mapper.repair_frames, map_window, merge,
                                lambda m: _consistency(cfg, lay, m, names))


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
        first = models[0]
        cons = _consistency(cfg, lay, first, names)
        if not cons.ok and cfg.mapper.on_break == "repair":
            # loop pairs are proposed where the model puts frames close together: a broken first pass proposes
            # few and wrong ones (measured on the default orbit: 1 verified instead of 6-10)
            fixed, info["first_pass_repair"] = _repair(cfg, lay, first, names, cons, work / "first_pass_repair",
                                                       progress)
            if fixed is not None:
                first = fixed
                models = [fixed, *models[1:]]
        pairs = model_loop_pairs(first, names, cfg)
        if pairs:
            before = num_verified(cfg, lay.database)
            with stderr_captured():  # the loop pairs' matching logs at INFO whatever glog's flags say
                colmap.match_pairs(cfg, lay.database, pairs, work / "loop_pairs.txt")
            info["loop_pairs"] = len(pairs)
            info["loop_pairs_verified"] = num_verified(cfg, lay.database) - before
            log.info("loop closure: %d candidate pairs, %d verified", len(pairs), info["loop_pairs_verified"])
            if info["loop_pairs_verified"] and cfg.matching.loop_remap:  # map again with the mapper that worked
                again = dataclasses.replace(cfg, mapper=dataclasses.replace(cfg.mapper, kind=result.mapper))
                models = colmap.reconstruct(again, lay.database, lay.images, work, names, progress).models
            elif info["loop_pairs_verified"]:  # the loop's tracks into the first model, one global adjustment
                with stderr_captured():  # the database cache and the global adjustment log at INFO regardless
                    info["loop_merge"] = merge_loop_tracks(first, lay.database,
                                                           colmap.incremental_options(cfg, names),
                                                           cfg.mapper.refine_loss_scale_px)
                models = [first, *models[1:]]
        info["seconds_loop_closure"] = time.perf_counter() - t0
    return models, info


def num_verified(cfg: SfMConfig, database: Path) -> int:
    """Pairs in ``database`` with at least ``matching.min_num_inliers`` verified matches."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    with pycolmap.Database.open(database) as db:
        _, geoms = db.read_two_view_geometries()
    return sum(len(g.inlier_matches) >= cfg.matching.min_num_inliers for g in geoms)


def write_model(rec: Any, path: Path) -> None:
    """Write a model as COLMAP binary into ``path`` by swapping a finished temporary folder in."""
    tmp = path.parent / f".{path.name}.tmp"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    rec.write_binary(str(tmp))
    if path.exists():
        shutil.rmtree(path)
    tmp.rename(path)

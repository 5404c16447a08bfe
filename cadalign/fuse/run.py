"""The fusion stage: frames (sim output or built dataset) -> semantic map, labelled mesh, report, pictures.

Outputs in ``OUT``::

    OUT/map.npz            the map (re-open and extend with cadalign.fuse.map_io.load_map)
    OUT/mesh.ply           labelled mesh: per-vertex colour, class and confidence (TSDF: marching cubes;
                           surfels: one square splat per surfel)
    OUT/points.ply         labelled point cloud
    OUT/views.png          ray-cast views of the mesh coloured by class and by observed colour
    OUT/fuse_report.json   frames, timings (frames/s), map size and, where the CAD truth is known, the
                           metrics of cadalign.metrics.map
    OUT/cadalign_stage.json  the resolved config and version

An interrupted run continues from the last map checkpoint; a finished one is reused; a folder made with
another config is refused unless ``overwrite``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from cadalign.config import to_dict
from cadalign.errors import InputError
from cadalign.fuse.base import LabelledGeometry, SemanticMap
from cadalign.fuse.config import FuseConfig
from cadalign.fuse.inputs import FrameSource, open_source
from cadalign.fuse.map_io import MapMeta, load_map, new_map, save_map, write_ply
from cadalign.fuse.predictors import depth_predictor, seg_predictor
from cadalign.fuse.views import render_views
from cadalign.io import prepare_stage_dir, write_json
from cadalign.metrics.map import load_truth, map_metrics, point_truth_labels, sample_surface, visible_mask
from cadalign.sfm.image_prep import read_prep
from cadalign.types import Progress

log = logging.getLogger(__name__)
REPORT = "fuse_report.json"


def fuse(source: FrameSource, cfg: FuseConfig, *, m: SemanticMap | None = None, meta: MapMeta | None = None,
         progress: Progress | None = None, checkpoint: Callable[[SemanticMap, MapMeta], None] | None = None,
         checkpoint_every: int = 50) -> tuple[SemanticMap, MapMeta, float]:
    """Integrate the frames of ``source`` not yet in ``meta`` into ``m`` (a new map when None).

    Returns the map, its metadata and the seconds spent in ``integrate`` (frame reading excluded). A
    KeyboardInterrupt (Ctrl-C) between frames first writes a checkpoint, so no fused frame is lost; one during a
    frame's integration does not (the map may hold part of that frame), and the last checkpoint stands.
    """
    m = m if m is not None else new_map(cfg, source.n_classes)
    meta = meta if meta is not None else MapMeta(source.classes.names, [], str(source.scene.dir))
    if tuple(meta.class_names) != tuple(source.classes.names):
        raise InputError(f"the map was made with classes {list(meta.class_names)}, the frames have "
                         f"{list(source.classes.names)}; fuse into a new map")
    done = set(meta.frame_ids)
    todo = [i for i in source.ids if i not in done]
    seconds = 0.0
    items = progress(todo, "fusing", len(todo)) if progress else todo
    busy = False  # True while a frame is being integrated: the map may then hold part of it
    try:
        for n, im_id in enumerate(items, start=1):
            frame = source.frame(im_id)
            t0 = time.perf_counter()
            busy = True
            m.integrate(frame)
            meta.frame_ids.append(int(im_id))
            busy = False
            seconds += time.perf_counter() - t0
            if checkpoint is not None and n % checkpoint_every == 0:
                checkpoint(m, meta)
    except KeyboardInterrupt:
        if checkpoint is not None and not busy:  # Ctrl-C between frames: keep every frame fused so far
            checkpoint(m, meta)
        raise
    return m, meta, seconds


def evaluate(source: FrameSource, cfg: FuseConfig, mesh: LabelledGeometry, points: LabelledGeometry,
             seed: int = 0) -> dict:
    """Map metrics against the scene's truth (see :mod:`cadalign.metrics.map`): the CAD for geometry, the
    scene's true depth for visibility and its class maps for the labels of surface points."""
    truth = load_truth(source.scene.dir)
    samples, _ = sample_surface(truth, spacing_m=max(cfg.voxel_m, 0.01), seed=seed)
    tol = max(1.5 * cfg.voxel_m, 0.03)
    geom = mesh if cfg.method == "tsdf" else points
    vis = np.zeros(len(samples), dtype=bool)
    votes_views = []
    for i in source.ids:
        meta = source.scene.frame(i)
        depth = source.scene.depth_m(i)
        vis |= visible_mask(samples, [(meta.camera, meta.T_cam_from_world, depth)], cfg.depth_min_m,
                            cfg.depth_max_m, tol)
        votes_views.append((meta.camera, meta.T_cam_from_world, depth, source.label_map(i)))
    point_truth = point_truth_labels(geom.points_m, votes_views, source.n_classes, cfg.depth_max_m, tol)
    out = map_metrics(geom.points_m, geom.labels, geom.faces, truth, samples[vis], point_truth=point_truth)
    out["visible_fraction_of_cad"] = float(vis.mean())
    out["evaluated_on"] = "mesh" if geom is mesh else "points"
    return out


def _timing(m: SemanticMap, frames: int, seconds: float) -> dict:
    parts = {k: round(v, 4) for k, v in getattr(m, "seconds", {}).items()}
    return {"frames": frames, "seconds_integrate": round(seconds, 4),
            "frames_per_second": round(frames / seconds, 3) if seconds > 0 else None, "seconds_by_part": parts}


def run(cfg: FuseConfig, source: Path, out_dir: Path, *, depth: str = "gt", labels: str = "gt",
        seg_model: Path | None = None, depth_model: Path | None = None, split: str | None = None,
        max_frames: int | None = None, id_range: tuple[int, int] | None = None, with_eval: bool = True,
        overwrite: bool = False, progress: Progress | None = None, checkpoint_every: int = 50,
        classes: Path | None = None) -> Path:
    """Fuse ``source`` into ``out_dir`` (layout in the module docstring); returns ``out_dir``. ``classes``: a JSON
    ``{obj_id: class name}`` for a plain BOP scene (default: objects.json, else one class per object id)."""
    out_dir = Path(out_dir)
    src = _open(cfg, source, depth, labels, seg_model, depth_model, split, max_frames, id_range, classes)
    config = {"fuse": to_dict(cfg), "source": str(src.scene.dir), "depth": depth, "labels": labels,
              "seg_model": str(seg_model) if seg_model else None,
              "depth_model": str(depth_model) if depth_model else None, "split": split, "max_frames": max_frames,
              "id_range": list(id_range) if id_range else None, "classes": list(src.classes.names)}
    if prepare_stage_dir(out_dir, "fuse", config, overwrite=overwrite) and (out_dir / REPORT).is_file():
        log.info("fusion already finished in %s; reusing it", out_dir)
        return out_dir
    (out_dir / REPORT).unlink(missing_ok=True)  # this run's mark of completion, not an older run's (--overwrite)
    map_path = out_dir / "map.npz"
    m, meta = load_map(map_path) if map_path.is_file() and not overwrite else (None, None)
    before = 0 if meta is None else len(meta.frame_ids)
    if meta is not None:
        log.info("continuing %s after %d frames", map_path, before)
    m, meta, seconds = fuse(src, cfg, m=m, meta=meta, progress=progress,
                            checkpoint=lambda mm, me: save_map(mm, me, map_path), checkpoint_every=checkpoint_every)
    save_map(m, meta, map_path)
    t0 = time.perf_counter()
    mesh, points = m.extract_mesh(), m.extract_points()
    write_ply(mesh, out_dir / "mesh.ply")
    write_ply(points, out_dir / "points.ply")
    report = {"method": cfg.method, "source": str(src.scene.dir), "depth": depth, "labels": src.labels_used,
              "classes": list(src.classes.names), "timing": _timing(m, len(meta.frame_ids) - before, seconds),
              "map": {"mesh_vertices": len(mesh), "mesh_faces": int(len(mesh.faces)), "points": len(points),
                      "origin": [float(x) for x in m.origin],
                      "label_histogram": np.bincount(mesh.labels, minlength=m.n_classes).tolist()},
              "seconds_extract": round(time.perf_counter() - t0, 3), "metrics": None}
    render_views(mesh, out_dir / "views.png", src.classes.names)
    if with_eval:
        if (src.scene.dir / "objects.json").is_file() and (src.scene.dir.parents[1] / "models").is_dir():
            report["metrics"] = evaluate(src, cfg, mesh, points)
        else:
            log.warning("no CAD truth next to %s (objects.json + models/): metrics skipped", src.scene.dir)
    write_json(out_dir / REPORT, report)
    return out_dir


def _open(cfg: FuseConfig, source: Path, depth: str, labels: str, seg_model: Path | None,
          depth_model: Path | None, split: str | None, max_frames: int | None,
          id_range: tuple[int, int] | None, classes: Path | None = None) -> FrameSource:
    # validates the choices and finds the classes
    src = open_source(source, depth=depth, labels=labels, label_confidence=cfg.label_confidence, split=split,
                      max_frames=max_frames, id_range=id_range, classes=classes)
    seg = dep = None
    prep = read_prep(src.scene.dir) if labels == "pred" or depth == "pred" else None  # raw frames get enhanced
    if labels == "pred" or (depth == "pred" and seg_model is not None):
        if seg_model is None:
            raise InputError("--labels pred needs a segmentation model: pass --model-seg RUN "
                             "(a `cadalign train seg` run folder or checkpoint)")

        seg = seg_predictor(seg_model, src.classes.names, source_prep=prep)
    if depth == "pred":
        if depth_model is None:
            raise InputError("--depth pred needs a depth model: pass --model-depth RUN "
                             "(a `cadalign train depth` run folder or checkpoint)")

        dep = depth_predictor(depth_model, seg, foreground_only=cfg.pred_depth_foreground_only and seg is not None,
                              source_prep=prep)
    return FrameSource(src.scene, src.classes, src.ids, src.depth, src.labels, src.label_confidence, dep,
                       seg if labels == "pred" else None)

"""Long surveys: map overlapping segments of the frame sequence separately, then merge them into one model.

Incremental mapping slows down faster than linearly with the number of frames and one weak stretch of a
long dive can hinge the whole model. With ``mapper.segment_frames = N`` the kept frames are cut into
windows of ``N`` frames that share ``mapper.segment_overlap`` frames with the next one
(:func:`plan_segments`); each window is mapped on its own (the same seeds, consistency check and retries as
a single model) from the one database of features and matches, so image ids agree across segments.

:func:`merge_models` then chains them: each segment is brought into the frame of the previous one by the
Sim(3) of their shared frames (:func:`frames_sim3`: orientations give the rotation, camera centres the
scale and translation), frames keep the pose of the first segment that registered
them, and the points are triangulated anew over the whole database with those poses (COLMAP's point
triangulator), so tracks run across segment borders. The refinement step that follows adjusts the merged
model as a whole. Each seam is reported: the frames it shares and how far their camera centres disagree
after the alignment, in median frame-to-frame steps.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.errors import DegenerateGeometryError
from cadalign.sfm.colmap_log import stderr_captured

log = logging.getLogger(__name__)


def plan_segments(n: int, length: int, overlap: int) -> list[range]:
    """The fewest windows of ``length`` consecutive indices that cover ``range(n)`` with each sharing at
    least ``overlap`` indices with the next, spread evenly (the first starts at 0, the last ends at ``n``).
    One window when ``n <= length``.

    Raises:
        ValueError: ``overlap`` is not in ``[3, length)`` (a Sim(3) needs three shared frames).
    """
    if not 3 <= overlap < length:
        raise ValueError(f"segment overlap must be >= 3 and < the segment length {length}, got {overlap}")
    if n <= length:
        return [range(n)]
    count = -(-(n - length) // (length - overlap)) + 1  # fewest windows whose overlaps are >= overlap
    starts = np.round(np.linspace(0, n - length, count)).astype(int)
    return [range(int(s), int(s) + length) for s in starts]


def _centres(rec: Any) -> dict[int, np.ndarray]:
    return {im.image_id: np.asarray(im.projection_center(), dtype=np.float64)
            for im in rec.images.values() if im.has_pose}


def frames_sim3(src: dict[int, Any], tgt: dict[int, Any]) -> tuple[np.ndarray, float, np.ndarray]:
    """``(R, s, t)`` with ``x_tgt = s R x_src + t`` from the frames both models registered (image id ->
    ``cam_from_world``): the rotation is the chordal mean of the frames' ``R_tgt^T R_src`` (each frame's
    orientation pins it, however short the shared stretch), then scale and translation are the
    least-squares fit of the camera centres under that rotation.

    Raises:
        DegenerateGeometryError: fewer than 3 shared frames.
    """
    shared = sorted(set(src) & set(tgt))
    if len(shared) < 3:
        raise DegenerateGeometryError(
            f"two SfM segments share only {len(shared)} registered frames; a merge needs 3. Raise "
            "mapper.segment_overlap or mapper.segment_frames, or map the survey as one model (segment_frames=0)")
    M = sum(tgt[i].rotation.matrix().T @ src[i].rotation.matrix() for i in shared)
    U, _, Vt = np.linalg.svd(M)
    R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    cs = np.array([src[i].inverse().translation for i in shared], dtype=np.float64)
    ct = np.array([tgt[i].inverse().translation for i in shared], dtype=np.float64)
    a, b = (cs - cs.mean(0)) @ R.T, ct - ct.mean(0)
    s = float(np.sum(a * b) / np.sum(a * a))
    return R, s, ct.mean(0) - s * R @ cs.mean(0)


def _poses(rec: Any) -> dict[int, Any]:
    return {im.image_id: im.cam_from_world() for im in rec.images.values() if im.has_pose}


def merge_models(models: list[Any], database: Path, images_dir: Path, work_dir: Path,
                 options: Any | None = None, adds: Sequence[set[str] | None] | None = None,
                 ) -> tuple[Any, list[dict[str, Any]]]:
    """One model from segment models (each a ``pycolmap.Reconstruction`` of the same database, in capture
    order); returns it and one record per seam. See the module doc. ``adds``: per model, the frames whose
    poses it may give (None: any); a model that only joins its neighbours still aligns them."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    base = models[0]
    cam_id = next(iter(base.cameras))
    poses: dict[int, tuple[str, Any]] = {im.image_id: (im.name, im.cam_from_world())
                                          for im in base.images.values() if im.has_pose}
    seams = []
    prev = base
    for k, rec in enumerate(models[1:], start=1):
        rec = pycolmap.Reconstruction(rec)
        R, s, t = frames_sim3(_poses(rec), _poses(prev))
        sim = pycolmap.Sim3d(s, pycolmap.Rotation3d(R), t)
        rec.transform(sim)
        c_prev, c_new = _centres(prev), _centres(rec)
        shared = sorted(set(c_prev) & set(c_new))
        steps = np.linalg.norm(np.diff(np.array([c_prev[i] for i in sorted(c_prev)]), axis=0), axis=1)
        step = float(np.median(steps)) if len(steps) else 1.0
        gap = [float(np.linalg.norm(c_prev[i] - c_new[i])) / step for i in shared]
        seams.append({"segment": k, "shared_frames": len(shared), "scale": s,
                      "centre_gap_steps_median": float(np.median(gap)) if gap else float("nan"),
                      "centre_gap_steps_max": float(np.max(gap)) if gap else float("nan")})
        allowed = adds[k] if adds is not None else None
        for im in rec.images.values():
            if im.has_pose and im.image_id not in poses and (allowed is None or im.name in allowed):
                poses[im.image_id] = (im.name, im.cam_from_world())
        prev = rec
    merged = pycolmap.Reconstruction()
    merged.add_camera_with_trivial_rig(base.cameras[cam_id])
    for image_id in sorted(poses):
        name, pose = poses[image_id]
        merged.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=cam_id, image_id=image_id), pose)
    work_dir.mkdir(parents=True, exist_ok=True)
    with stderr_captured():  # logs at INFO whatever glog's flags say
        merged = pycolmap.triangulate_points(merged, database, images_dir, work_dir, clear_points=True,
                                             options=options or pycolmap.IncrementalPipelineOptions(),
                                             refine_intrinsics=True)
    log.info("merged %d SfM segments: %d frames, %d points; seams %s", len(models), merged.num_reg_images(),
             merged.num_points3D(), ", ".join(f"{s['centre_gap_steps_median']:.3f}" for s in seams))
    return merged, seams


def map_in_segments(names: list[str], length: int, overlap: int,
                    map_one: Callable[[list[str], int], tuple[Any, dict[str, Any]]],
                    merge: Callable[[list[Any]], tuple[Any, list[dict[str, Any]]]]) -> tuple[Any, dict[str, Any]]:
    """Map each window of ``names`` with ``map_one(names, k)`` -> (model, info), then ``merge`` the models;
    returns the merged model and a report of the segments and seams."""
    windows = plan_segments(len(names), length, overlap)
    models, infos = [], []
    for k, w in enumerate(windows):
        sub = [names[i] for i in w]
        log.info("SfM segment %d/%d: frames %s..%s", k + 1, len(windows), sub[0], sub[-1])
        model, info = map_one(sub, k)
        models.append(model)
        infos.append({"frames": [sub[0], sub[-1]], "registered": model.num_reg_images(),
                      "breaks": len(info.get("consistency", {}).get("breaks", [])),
                      "loop_pairs_verified": int(info.get("loop_pairs_verified", 0))})
    merged, seams = merge(models)
    return merged, {"segments": infos, "seams": seams}

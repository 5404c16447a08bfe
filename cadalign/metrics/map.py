"""Accuracy and completeness of a fused semantic map against the CAD (simulator / dataset) truth.

Truth is the posed CAD parts of the scene (BOP ``models/obj_XXXXXX.ply`` in mm, placed by ``objects.json``).
Only the *visible* CAD surface counts for completeness: CAD surface samples (a uniform area sampling) that
at least one frame sees, i.e. that project inside the image within the fusion depth range and agree with the
frame's true depth there to within ``visibility_tol_m``.

Metrics (distances in metres):

- ``completeness_within_{2,5}cm``: fraction of the visible CAD samples whose distance to the fused surface is
  at most 2 / 5 cm; ``completeness_mean_m`` their mean distance (truncated at ``trunc_m``).
- ``accuracy_mean_m``: mean distance to the CAD of the fused points that lie within ``trunc_m`` of it (the
  rest is seabed or other non-CAD geometry, counted in ``fused_fraction_on_cad``).
- ``chamfer_m``: the mean of the two truncated mean distances above.
- Labels are judged on *surface points*: fused points that some frame sees (they agree with its true depth
  to ``visibility_tol_m``), whose true class is the majority of the simulator's per-pixel class maps there
  (:func:`point_truth_labels`). ``label_accuracy`` is over all of them, ``label_accuracy_on_cad`` over those
  within ``label_tol_m`` of the CAD (the structure itself, without the seabed), ``miou`` the mean per-class
  IoU over classes present in truth or prediction. Without class maps, truth falls back to the class of the
  nearest CAD part within ``label_tol_m``, else background.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from cadalign.errors import InputError
from cadalign.io import read_json
from cadalign.types import Camera, Rigid3


@dataclass(frozen=True)
class CadTruth:
    """Posed CAD parts in world metres: per part (vertices (V, 3), faces (F, 3), class index)."""

    parts: tuple[tuple[np.ndarray, np.ndarray, int], ...]
    class_names: tuple[str, ...]


def load_truth(scene_dir: Path) -> CadTruth:
    """The posed CAD parts of a sim or dataset scene (``../../models`` + ``objects.json``)."""

    scene_dir = Path(scene_dir)
    objects = read_json(scene_dir / "objects.json")
    models = scene_dir.parents[1] / "models"
    parts = []
    cache: dict[int, trimesh.Trimesh] = {}
    for o in objects["objects"]:
        oid = int(o["obj_id"])
        path = models / f"obj_{oid:06d}.ply"
        if not path.is_file():
            raise InputError(f"{path} is missing: the CAD truth needs the scene's BOP models folder")
        if oid not in cache:
            cache[oid] = trimesh.load(path, force="mesh", process=False)
        T = Rigid3(np.reshape(o["R_world_from_obj"], (3, 3)), o["t_world_from_obj_m"])
        verts = T.apply(np.asarray(cache[oid].vertices, dtype=np.float64) / 1000.0)  # BOP models are in mm
        parts.append((verts, np.asarray(cache[oid].faces, dtype=np.int64), int(o["class_id"])))
    if not parts:
        raise InputError(f"{scene_dir}/objects.json lists no objects: nothing to compare the map with")
    return CadTruth(tuple(parts), tuple(objects["classes"]))


def sample_surface(truth: CadTruth, spacing_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Area-uniform samples (about one per ``spacing_m``^2) of every part: points (N, 3) and class (N,)."""
    rng = np.random.default_rng(seed)
    pts, cls = [], []
    for verts, faces, class_id in truth.parts:
        tri = verts[faces]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        n = max(int(np.ceil(area.sum() / spacing_m**2)), 1)
        face = rng.choice(len(faces), size=n, p=area / area.sum())
        r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
        t = tri[face]
        pts.append((1 - r1)[:, None] * t[:, 0] + (r1 * (1 - r2))[:, None] * t[:, 1] + (r1 * r2)[:, None] * t[:, 2])
        cls.append(np.full(n, class_id, dtype=np.int64))
    return np.concatenate(pts), np.concatenate(cls)


def _in_view(points: np.ndarray, cam: Camera, T: Rigid3, z_min_m: float,
             z_max_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points that project into ``cam`` at ``T`` (camera-frame depth in ``(z_min_m, z_max_m]``): their
    indices, pixel columns and rows (``floor`` of the projection: pixel centres at +0.5) and depths.

    Only the points in the depth range are divided and rounded (the same arithmetic per point as on all of
    them), so a view that sees a small part of a large cloud costs little beyond the transform."""
    pc = T.apply(points)
    z = pc[:, 2]
    idx = np.flatnonzero((z > z_min_m) & (z <= z_max_m))
    zi = z[idx]
    u = np.floor(pc[idx, 0] / zi * cam.fx + cam.cx).astype(np.int64)
    v = np.floor(pc[idx, 1] / zi * cam.fy + cam.cy).astype(np.int64)
    keep = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return idx[keep], u[keep], v[keep], zi[keep]


def visible_mask(points: np.ndarray, views: Iterable[tuple[Camera, Rigid3, np.ndarray]], depth_min_m: float,
                 depth_max_m: float, tol_m: float) -> np.ndarray:
    """(N,) bool: the point agrees with the true depth of at least one view ``(camera, T_cam_from_world, depth)``."""
    seen = np.zeros(len(points), dtype=bool)
    for cam, T, depth in views:
        idx, u, v, z = _in_view(points, cam, T, depth_min_m, depth_max_m)
        seen[idx[np.abs(np.asarray(depth)[v, u] - z) <= tol_m]] = True
    return seen


def point_truth_labels(points: np.ndarray, views: Iterable[tuple[Camera, Rigid3, np.ndarray, np.ndarray]],
                       n_classes: int, depth_max_m: float, tol_m: float) -> np.ndarray:
    """(N,) true class of each point: the majority over the views ``(camera, T_cam_from_world, depth, class map)``
    that see it (depth agrees to ``tol_m``); -1 where no view sees it."""
    votes = np.zeros(len(points) * n_classes, dtype=np.int64)
    keys: list[np.ndarray] = []
    pending = 0
    for cam, T, depth, cls in views:
        idx, u, v, z = _in_view(points, cam, T, 0.0, depth_max_m)
        ok = np.abs(np.asarray(depth)[v, u] - z) <= tol_m
        keys.append(idx[ok] * n_classes + np.asarray(cls)[v[ok], u[ok]])
        pending += len(keys[-1])
        if pending > len(votes):  # count in batches: one bincount per view would clear all N x C counters
            votes += np.bincount(np.concatenate(keys), minlength=len(votes))
            keys, pending = [], 0
    if keys:
        votes += np.bincount(np.concatenate(keys), minlength=len(votes))
    votes = votes.reshape(len(points), n_classes)
    return np.where(votes.sum(axis=1) > 0, votes.argmax(axis=1), -1)


def _distance_to_mesh(query: np.ndarray,
                      parts: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Exact distance of each query point to the union of triangle meshes, and the index of the nearest one."""
    import open3d as o3d  # lazy: heavy dependency (open3d)

    centre = np.mean([v.mean(axis=0) for v, _ in parts], axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    ids = {}
    for k, (v, f) in enumerate(parts):
        m = o3d.t.geometry.TriangleMesh()
        m.vertex.positions = o3d.core.Tensor((v - centre).astype(np.float32))
        m.triangle.indices = o3d.core.Tensor(np.asarray(f, dtype=np.int32))
        ids[scene.add_triangles(m)] = k
    q = o3d.core.Tensor((query - centre).astype(np.float32))
    ans = scene.compute_closest_points(q)
    d = np.linalg.norm(ans["points"].numpy() - (query - centre), axis=1)
    lut = np.zeros(max(ids) + 1, dtype=np.int64)
    for gid, k in ids.items():
        lut[gid] = k
    return d, lut[ans["geometry_ids"].numpy().astype(np.int64)]


def _distance_to_points(query: np.ndarray, points: np.ndarray) -> np.ndarray:
    return cKDTree(points).query(query, k=1, workers=1)[0]


def map_metrics(points_m: np.ndarray, labels: np.ndarray, faces: np.ndarray | None, truth: CadTruth,
                visible_pts: np.ndarray, *, point_truth: np.ndarray | None = None, trunc_m: float = 0.1,
                label_tol_m: float = 0.05) -> dict[str, float]:
    """Metrics of a fused map (points + labels, optionally mesh faces) against the CAD truth (module docstring)."""
    if len(points_m) == 0:
        raise InputError("the fused map is empty: nothing to evaluate")
    if len(visible_pts) == 0:
        raise InputError("no CAD surface is visible in the frames: check the poses and the depth range")
    if faces is not None and len(faces):
        d_comp = _distance_to_mesh(visible_pts, [(points_m, faces)])[0]
    else:
        d_comp = _distance_to_points(visible_pts, points_m)
    d_acc, part = _distance_to_mesh(points_m, [(v, f) for v, f, _ in truth.parts])
    part_class = np.array([c for _, _, c in truth.parts], dtype=np.int64)[part]
    on_cad = d_acc <= trunc_m
    near = d_acc <= label_tol_m
    truth_cls = np.where(near, part_class, 0) if point_truth is None else np.asarray(point_truth)
    known = truth_cls >= 0
    tl, pl = truth_cls[known], np.asarray(labels)[known]
    ious = {}
    for c in np.union1d(np.unique(tl), np.unique(pl)):
        union = np.sum((tl == c) | (pl == c))
        ious[int(c)] = float(np.sum((tl == c) & (pl == c)) / union) if union else float("nan")
    on_cad_known = known & near
    comp_mean = float(np.minimum(d_comp, trunc_m).mean())
    acc_mean = float(d_acc[on_cad].mean()) if on_cad.any() else float("nan")
    names = truth.class_names
    return {
        "n_fused_points": int(len(points_m)), "n_visible_cad_samples": int(len(visible_pts)),
        "completeness_within_2cm": float(np.mean(d_comp <= 0.02)),
        "completeness_within_5cm": float(np.mean(d_comp <= 0.05)),
        "completeness_mean_m": comp_mean, "accuracy_mean_m": acc_mean,
        "accuracy_within_2cm": float(np.mean(d_acc[on_cad] <= 0.02)) if on_cad.any() else float("nan"),
        "fused_fraction_on_cad": float(on_cad.mean()),
        "chamfer_m": float((comp_mean + acc_mean) / 2) if on_cad.any() else float("nan"),
        "label_accuracy": float(np.mean(tl == pl)) if known.any() else float("nan"),
        "label_accuracy_on_cad": float(np.mean(labels[on_cad_known] == truth_cls[on_cad_known]))
        if on_cad_known.any() else float("nan"),
        "label_points": int(known.sum()), "label_truth": "nearest CAD part" if point_truth is None else "class maps",
        "miou": float(np.nanmean(list(ious.values()))),
        "iou_per_class": {(names[c] if c < len(names) else str(c)): v for c, v in ious.items()},
        "trunc_m": trunc_m, "label_tol_m": label_tol_m,
    }

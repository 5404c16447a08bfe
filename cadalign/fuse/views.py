"""Pictures of a labelled mesh: ray-cast views coloured by class and by observed colour (no GL needed)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cadalign.errors import InputError
from cadalign.fuse.base import LabelledGeometry
from cadalign.io import write_image

PALETTE = np.array([
    [140, 140, 140], [31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189],
    [140, 86, 75], [227, 119, 194], [188, 189, 34], [23, 190, 207],
], dtype=np.uint8)


def class_colors(labels: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colours of class indices (background grey, then a fixed categorical palette)."""
    return PALETTE[np.asarray(labels) % len(PALETTE)]


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(3, 3) rotation world_from_cam for a camera at ``eye`` looking at ``target`` (x right, y down, z fwd)."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0, 0])
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _scene(mesh: LabelledGeometry) -> tuple[Any, np.ndarray]:
    """An Open3D ray-casting scene of ``mesh`` (vertices about their mean, for float32) and that centre."""
    import open3d as o3d  # lazy: heavy dependency (open3d)

    if mesh.faces is None or len(mesh.faces) == 0:
        raise InputError("render_view needs a mesh with faces")
    centre = mesh.points_m.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    tm = o3d.t.geometry.TriangleMesh()
    tm.vertex.positions = o3d.core.Tensor((mesh.points_m - centre).astype(np.float32))
    tm.triangle.indices = o3d.core.Tensor(mesh.faces.astype(np.int32))
    scene.add_triangles(tm)
    return scene, centre


def _cast(scene: Any, centre: np.ndarray, eye: np.ndarray, target: np.ndarray, size: tuple[int, int],
          hfov_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view's rays cast into ``scene``: (H, W) hit mask, (H, W) hit triangle (0 where none), (H, W) shade."""
    import open3d as o3d  # lazy: heavy dependency (open3d)

    w, h = size
    f = 0.5 * w / np.tan(np.radians(hfov_deg) / 2)
    uu, vv = np.meshgrid((np.arange(w) + 0.5 - w / 2) / f, (np.arange(h) + 0.5 - h / 2) / f)
    R = _look_at(np.asarray(eye, float), np.asarray(target, float))
    d = np.stack([uu, vv, np.ones_like(uu)], -1) @ R.T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(eye - centre, d.shape), d], -1).astype(np.float32)
    ans = scene.cast_rays(o3d.core.Tensor(rays))
    hit = np.isfinite(ans["t_hit"].numpy())
    prim = np.where(hit, ans["primitive_ids"].numpy(), 0).astype(np.int64)
    shade = np.abs(np.einsum("hwk,hwk->hw", ans["primitive_normals"].numpy(), d))
    return hit, prim, shade


def _paint(mesh: LabelledGeometry, hit: np.ndarray, prim: np.ndarray, shade: np.ndarray,
           by_class: bool) -> np.ndarray:
    vert = mesh.faces[prim, 0]
    base = class_colors(mesh.labels[vert]) if by_class else mesh.colors[vert]
    img = (base.astype(np.float32) * (0.35 + 0.65 * shade[..., None])).clip(0, 255).astype(np.uint8)
    img[~hit] = 255
    return img


def render_view(mesh: LabelledGeometry, eye: np.ndarray, target: np.ndarray, size: tuple[int, int],
                hfov_deg: float = 60.0, by_class: bool = True) -> np.ndarray:
    """(H, W, 3) uint8 picture of ``mesh`` from ``eye``: class or observed colour, Lambert-shaded, white sky."""
    scene, centre = _scene(mesh)
    return _paint(mesh, *_cast(scene, centre, eye, target, size, hfov_deg), by_class)


def render_views(mesh: LabelledGeometry, path: Path, class_names: Sequence[str], *, n_views: int = 3,
                 size: tuple[int, int] = (480, 360)) -> Path:
    """A PNG grid: ``n_views`` views around the mesh (top row by class, bottom row observed colour) + legend.

    The views frame the labelled (non-background) part of the map when it has one, so a large seabed does
    not shrink the structure to a few pixels."""

    fg = mesh.points_m[mesh.labels != 0]
    lo, hi = np.percentile(fg if len(fg) >= 100 else mesh.points_m, [1, 99], axis=0)
    target = (lo + hi) / 2
    radius = max(float(np.linalg.norm(hi - lo)), 1e-3)
    rows: list[list[np.ndarray]] = [[], []]
    scene, centre = _scene(mesh)  # one BVH for all views; each view cast once, painted both ways
    for k in range(n_views):
        a = 2 * np.pi * k / n_views + np.pi / 6
        eye = target + 1.1 * radius * np.array([np.cos(a), np.sin(a), 0.55])
        cast = _cast(scene, centre, eye, target, size, 60.0)
        for r, by_class in enumerate((True, False)):
            rows[r].append(_paint(mesh, *cast, by_class))
    grid = np.concatenate([np.concatenate(r, axis=1) for r in rows], axis=0)
    legend = np.full((28, grid.shape[1], 3), 255, np.uint8)
    x = 8
    for c, name in enumerate(class_names):
        cv2.rectangle(legend, (x, 6), (x + 16, 22), tuple(int(v) for v in class_colors([c])[0]), -1)
        cv2.putText(legend, name, (x + 22, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
        x += 30 + 9 * len(name)
    return write_image(Path(path), np.ascontiguousarray(np.concatenate([legend, grid], axis=0)))

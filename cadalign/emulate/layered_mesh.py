"""Layered mesh from one image (GenLaM): depth + K -> back-projection -> grid triangles -> layers + panes.

Every pixel centre with valid depth becomes a vertex (``K^-1 (u + 0.5, v + 0.5, 1) * z``, camera frame:
x right, y down, z forward). Each 2x2 block of pixels ``a b / c d`` gives the triangles ``(a, c, b)`` and
``(b, c, d)`` (normals towards the camera). A triangle is cut when a corner has no depth or when it spans
a depth discontinuity: ``(z_max - z_min) > rel_jump * z_min``. Faces carry layers: RGB (mean of corners;
the vertex colours are kept for barycentric interpolation), class and part (majority of the corners) and
``pane`` (0; the panes of :mod:`cadalign.emulate.panes` replace the faces inside their masks and get ids
1, 2, ...). With a camera pose the mesh is moved to the world frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from cadalign.config import bounded
from cadalign.emulate.mesh import LayeredMesh, concatenate
from cadalign.emulate.panes import PaneConfig, PaneResult, extract_panes
from cadalign.errors import InputError
from cadalign.geometry import depth_to_points

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ImageInput:
    """One RGB-D frame to lift into a layered mesh.

    Attributes:
        rgb: (H, W, 3) uint8.
        depth_m: (H, W) z-depth in metres (<= 0 / non-finite = invalid).
        K: (3, 3) intrinsics (pixel centres at integer + 0.5).
        class_id: optional (H, W) class per pixel.
        part_id: optional (H, W) part / instance id per pixel.
        pane_mask: optional (H, W) bool mask of planar panes (windows, glass, flat panels).
        T_world_from_cam: optional (4, 4) pose of the camera; the mesh stays in the camera frame when None.
        class_names: names of the class ids.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    K: np.ndarray
    class_id: np.ndarray | None = None
    part_id: np.ndarray | None = None
    pane_mask: np.ndarray | None = None
    T_world_from_cam: np.ndarray | None = None
    class_names: tuple[str, ...] = ()


@dataclass(frozen=True)
class LayeredMeshConfig:
    rel_jump: float = bounded(0.05, gt=0.0)
    """Cut a triangle whose corner depths differ by more than this fraction of the nearest one."""
    min_depth_m: float = bounded(0.0, ge=0.0)
    """Pixels nearer than this count as invalid, metres."""
    max_depth_m: float = bounded(1e6, gt=0.0)
    """Pixels farther than this count as invalid (e.g. open water), metres."""
    stride: int = bounded(1, ge=1)
    """Use every stride-th pixel in both directions (coarser, smaller meshes)."""
    panes: bool = True
    """Build planar panes from the pane mask when the input has one."""
    pane: PaneConfig = field(default_factory=PaneConfig)
    """Pane thresholds (Algorithm 1)."""


PRESETS: dict[str, LayeredMeshConfig] = {
    "default": LayeredMeshConfig(),
    "coarse": LayeredMeshConfig(stride=2),
    "strict": LayeredMeshConfig(rel_jump=0.02),
}


def _check(inp: ImageInput) -> tuple[np.ndarray, np.ndarray]:
    depth = np.asarray(inp.depth_m, dtype=np.float64)
    rgb = np.asarray(inp.rgb)
    if depth.ndim != 2 or rgb.shape[:2] != depth.shape or rgb.ndim != 3 or rgb.shape[2] < 3:
        raise InputError(f"image source: rgb {rgb.shape} must be (H, W, 3) and depth {depth.shape} (H, W)")
    for name in ("class_id", "part_id", "pane_mask"):
        a = getattr(inp, name)
        if a is not None and np.shape(a) != depth.shape:
            raise InputError(f"image source: {name} has shape {np.shape(a)}; expected {depth.shape}")
    return depth, rgb[..., :3].astype(np.uint8)


def _strided(a: np.ndarray | None, s: int) -> np.ndarray | None:
    return None if a is None else np.asarray(a)[::s, ::s]


def _majority(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Per element: the value shared by two of three (the first when all differ)."""
    return np.where(b == c, b, a)


def grid_faces(depth: np.ndarray, valid: np.ndarray, rel_jump: float) -> np.ndarray:
    """(F, 3) pixel-index triangles ``row * W + col`` of the depth grid, cut at invalid pixels and jumps."""
    H, W = depth.shape
    idx = np.arange(H * W).reshape(H, W)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    z, ok = depth.ravel(), valid.ravel()
    keep = ok[tris].all(1)
    zt = np.where(keep[:, None], z[tris], 1.0)
    keep &= zt.max(1) - zt.min(1) <= rel_jump * zt.min(1)
    return tris[keep]


def mesh_from_image(inp: ImageInput, cfg: LayeredMeshConfig) -> LayeredMesh:
    """The layered mesh of one RGB-D image (see the module docstring)."""
    depth, rgb = _check(inp)
    s = cfg.stride
    K = np.asarray(inp.K, dtype=np.float64).copy()
    if s > 1:  # pixel (i, j) of the strided grid is pixel (s i, s j) of the original: its centre s i + 0.5
        K[0, 2] = (K[0, 2] - 0.5) / s + 0.5
        K[1, 2] = (K[1, 2] - 0.5) / s + 0.5
        K[0, 0] /= s
        K[1, 1] /= s
    depth, rgb = depth[::s, ::s], rgb[::s, ::s]
    cls, part, pane_mask = _strided(inp.class_id, s), _strided(inp.part_id, s), _strided(inp.pane_mask, s)
    pts, valid = depth_to_points(K, depth)
    valid &= (depth >= cfg.min_depth_m) & (depth <= cfg.max_depth_m)
    tris = grid_faces(depth, valid, cfg.rel_jump)
    H, W = depth.shape
    cls_f = np.zeros(H * W, np.int32) if cls is None else cls.ravel().astype(np.int32)
    part_f = np.zeros(H * W, np.int32) if part is None else part.ravel().astype(np.int32)
    panes = None
    if cfg.panes and pane_mask is not None and np.any(pane_mask):
        panes = extract_panes(pane_mask.astype(bool), pts, valid, cfg.pane)
        inside = np.isin(panes.labels, [p.label for p in panes.panes]).ravel()
        tris = tris[inside[tris].sum(1) < 2]  # the pane replaces the grid faces inside it
    if len(tris) == 0:
        raise InputError(f"image source {depth.shape[1]}x{depth.shape[0]}: no triangle survives (no two neighbouring "
                         "pixels with valid depth within rel_jump); check the depth map and its unit (metres)")
    used, remap = np.unique(tris, return_inverse=True)
    faces = remap.reshape(-1, 3)
    rgb_f = rgb.reshape(-1, 3)
    face_rgb = np.rint(rgb_f[tris].astype(np.float64).mean(1)).astype(np.uint8)
    t = tris.T
    mesh = LayeredMesh(pts.reshape(-1, 3)[used], faces, face_rgb, _majority(*cls_f[t]), _majority(*part_f[t]),
                       np.zeros(len(faces)), rgb_f[used], inp.class_names)
    if panes is not None and panes.panes:
        mesh = concatenate([mesh] + _pane_meshes(panes, rgb_f, cls_f, part_f))
    log.info("layered mesh: %d vertices, %d faces, %d panes", len(mesh.vertices_m), mesh.n_faces,
             0 if panes is None else len(panes.panes))
    if inp.T_world_from_cam is not None:
        T = np.asarray(inp.T_world_from_cam, dtype=np.float64)
        mesh = mesh.transformed(T[:3, :3], T[:3, 3])
    return mesh


def _mode(values: np.ndarray) -> int:
    vals, counts = np.unique(values, return_counts=True)
    return int(vals[np.argmax(counts)]) if len(vals) else 0


def _pane_meshes(panes: PaneResult, rgb_f: np.ndarray, cls_f: np.ndarray, part_f: np.ndarray) -> list[LayeredMesh]:
    """One layered mesh per pane: colour = mean over its pixels, class and part = their mode, pane id k."""
    out = []
    for k, p in enumerate(panes.panes, start=1):
        pix = np.flatnonzero(panes.labels.ravel() == p.label)
        colour = np.rint(rgb_f[pix].astype(np.float64).mean(0)).astype(np.uint8)
        n = len(p.faces)
        out.append(LayeredMesh(p.vertices_m, p.faces, np.tile(colour, (n, 1)), np.full(n, _mode(cls_f[pix])),
                               np.full(n, _mode(part_f[pix])), np.full(n, k),
                               np.tile(colour, (len(p.vertices_m), 1))))
    return out

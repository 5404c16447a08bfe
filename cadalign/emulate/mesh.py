"""The mesh every emulated sensor casts rays against: triangles in the world with per-face layers.

Layers (GenLaM's "layered mesh"): colour, semantic class, part id and pane id per face, plus optional
per-vertex colour interpolated with the hit's barycentrics. A hit on face ``f`` at barycentrics ``(u, v)``
(point ``(1 - u - v) A + u B + v C`` of the triangle ``(A, B, C)``) therefore carries everything a sensor
needs: range, colour, class, part and whether it is a planar pane.

Conventions: ``part_id`` is the scene instance id (object ``k`` of a scene spec has part ``k + 1``; 0 is
background geometry such as the seabed); ``pane_id`` is 0 for ordinary faces and ``k >= 1`` for the faces
of planar pane ``k`` (:mod:`cadalign.emulate.panes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cadalign.errors import InputError


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class LayeredMesh:
    """Triangles with per-face layers, in metres.

    Attributes:
        vertices_m: (V, 3) float64 positions (world frame, or camera frame for a mesh from one image).
        faces: (F, 3) int64 vertex indices.
        face_rgb: (F, 3) uint8 colour per face.
        class_id: (F,) int32 semantic class per face (0 = background).
        part_id: (F,) int32 part / instance id per face (0 = background geometry).
        pane_id: (F,) int32 planar pane per face (0 = not a pane).
        vertex_rgb: optional (V, 3) uint8 colour per vertex; when given, hits interpolate it with their
            barycentrics instead of using ``face_rgb``.
        class_names: names of the class ids (index = id), for legends.
    """

    vertices_m: np.ndarray
    faces: np.ndarray
    face_rgb: np.ndarray
    class_id: np.ndarray
    part_id: np.ndarray
    pane_id: np.ndarray
    vertex_rgb: np.ndarray | None = None
    class_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices_m, dtype=np.float64)
        f = np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
            raise InputError(f"LayeredMesh: vertices_m must be a finite (V, 3) array, got shape {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or (f.size and not np.issubdtype(f.dtype, np.integer)):
            raise InputError(f"LayeredMesh: faces must be an integer (F, 3) array, got {f.dtype} {f.shape}")
        f = f.astype(np.int64)
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise InputError(f"LayeredMesh: face indices must lie in [0, {len(v)})")
        n = len(f)
        object.__setattr__(self, "vertices_m", _frozen(v))
        object.__setattr__(self, "faces", _frozen(f))
        object.__setattr__(self, "face_rgb", _frozen(_layer(self.face_rgb, (n, 3), np.uint8, "face_rgb")))
        for name in ("class_id", "part_id", "pane_id"):
            object.__setattr__(self, name, _frozen(_layer(getattr(self, name), (n,), np.int32, name)))
        if self.vertex_rgb is not None:
            vr = _layer(self.vertex_rgb, (len(v), 3), np.uint8, "vertex_rgb")
            object.__setattr__(self, "vertex_rgb", _frozen(vr))
        object.__setattr__(self, "class_names", tuple(self.class_names))

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def face_normals(self) -> np.ndarray:
        """(F, 3) unit normals ``(B - A) x (C - A)``; zero for degenerate faces."""
        tri = self.vertices_m[self.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)

    def hit_rgb(self, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """(N, 3) uint8 colour of hits on ``face`` (N,) at barycentrics ``bary`` (N, 2); face < 0 -> black."""
        face = np.asarray(face, dtype=np.int64)
        hit = face >= 0
        if self.vertex_rgb is None:
            out = self.face_rgb[np.maximum(face, 0)]
            out[~hit] = 0
            return out
        out = np.zeros((len(face), 3), dtype=np.uint8)
        uv = np.asarray(bary, dtype=np.float64)[hit]
        w = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        cols = self.vertex_rgb[self.faces[face[hit]]].astype(np.float64)  # (M, 3 corners, 3 channels)
        out[hit] = np.clip(np.rint(np.einsum("mk,mkc->mc", w, cols)), 0, 255).astype(np.uint8)
        return out

    def transformed(self, R: np.ndarray, t: np.ndarray) -> LayeredMesh:
        """The same mesh with vertices mapped by ``x -> R x + t`` (e.g. camera frame -> world)."""
        v = self.vertices_m @ np.asarray(R, dtype=np.float64).T + np.asarray(t, dtype=np.float64)
        return LayeredMesh(v, self.faces, self.face_rgb, self.class_id, self.part_id, self.pane_id,
                           self.vertex_rgb, self.class_names)


def _layer(a: np.ndarray, shape: tuple[int, ...], dtype: type, name: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.shape != shape:
        raise InputError(f"LayeredMesh: {name} must have shape {shape}, got {arr.shape}")
    return arr.astype(dtype)


def concatenate(meshes: list[LayeredMesh]) -> LayeredMesh:
    """One mesh holding every input mesh (vertex colours kept only when every input has them)."""
    if not meshes:
        raise InputError("nothing to concatenate: the mesh list is empty")
    offsets = np.cumsum([0] + [len(m.vertices_m) for m in meshes[:-1]])
    vrgb = None
    if all(m.vertex_rgb is not None for m in meshes):
        vrgb = np.concatenate([m.vertex_rgb for m in meshes])
    names = max((m.class_names for m in meshes), key=len)
    return LayeredMesh(
        np.concatenate([m.vertices_m for m in meshes]),
        np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]),
        np.concatenate([m.face_rgb for m in meshes]),
        np.concatenate([m.class_id for m in meshes]),
        np.concatenate([m.part_id for m in meshes]),
        np.concatenate([m.pane_id for m in meshes]),
        vrgb,
        names,
    )

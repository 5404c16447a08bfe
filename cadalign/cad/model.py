"""The in-memory CAD model: a triangle mesh in metres with part labels and a symmetry.

Every :class:`CadModel` is in metres whatever unit its file was in (``unit``
records the source unit). Arrays are read-only; derived quantities (bounding
box, diameter) are computed on demand and cached.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from cadalign.cad.symmetry import Symmetry
from cadalign.cad.units import UNIT_TO_M
from cadalign.errors import InputError

__all__ = ["CadModel", "Symmetry", "max_pairwise_distance"]


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def _pairwise_max(points: np.ndarray, chunk: int = 2048) -> float:
    """Exact max distance between rows of ``points`` (N, D), in chunks to bound memory."""
    best = 0.0
    for i in range(0, len(points), chunk):
        block = points[i : i + chunk]
        d2 = ((block[:, None, :] - points[None, :, :]) ** 2).sum(-1)
        best = max(best, float(d2.max()))
    return float(np.sqrt(best))


def max_pairwise_distance(points: np.ndarray) -> float:
    """Exact diameter of a point set: the largest distance between two of its points.

    The farthest pair always lies on the convex hull, so only hull vertices are
    compared. Flat or collinear sets (where a 3D hull is undefined) are handled
    in their 2D or 1D principal subspace, where the same holds.

    Args:
        points: (N, 3) coordinates.

    Returns:
        the diameter in the points' unit (0.0 for fewer than two points).
    """
    pts = np.unique(np.asarray(points, dtype=np.float64), axis=0)
    if len(pts) < 2:
        return 0.0
    centred = pts - pts.mean(axis=0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    rank = int((s > s[0] * 1e-9).sum())
    if rank == 1:
        proj = centred @ vt[0]
        return float(proj.max() - proj.min())
    coords = centred if rank == 3 else centred @ vt[:2].T
    try:
        hull = ConvexHull(coords)
        cand = coords[hull.vertices]
    except QhullError:
        cand = coords  # nearly degenerate: fall back to the exact O(N^2) scan
    return _pairwise_max(cand)


def _check_colors(c: np.ndarray | None, n: int, name: str) -> np.ndarray | None:
    if c is None:
        return None
    c = np.asarray(c)
    if c.ndim != 2 or c.shape[0] != n or c.shape[1] not in (3, 4):
        raise InputError(f"{name} must have shape ({n}, 4), got {c.shape}")
    if c.shape[1] == 3:
        c = np.concatenate([c, np.full((n, 1), 255, dtype=c.dtype)], axis=1)
    return _frozen(c.astype(np.uint8))


@dataclass(frozen=True, eq=False)
class CadModel:
    """A CAD model as a triangle mesh in metres, with per-face part labels.

    Attributes:
        name: model name (defaults to the file stem).
        vertices_m: (V, 3) float64 vertex positions in metres, model frame.
        faces: (F, 3) int64 vertex indices, counter-clockwise seen from outside.
        unit: the unit the source file was in: ``m``, ``cm``, ``mm`` or ``in``.
        source: the file it was loaded from, if any.
        part_labels: (F,) int32 part index of each face, in ``0..P-1``.
        part_names: (P,) names of the parts (scene nodes of the file).
        class_name: semantic class (e.g. ``valve``); defaults to ``name``.
        symmetry: the object's symmetry (BOP convention).
        vertex_colors: optional (V, 4) uint8 RGBA per vertex.
        face_colors: optional (F, 4) uint8 RGBA per face.
    """

    name: str
    vertices_m: np.ndarray
    faces: np.ndarray
    unit: str = "m"
    source: Path | None = None
    part_labels: np.ndarray | None = None
    part_names: tuple[str, ...] = ()
    class_name: str = ""
    symmetry: Symmetry = field(default_factory=Symmetry.none)
    vertex_colors: np.ndarray | None = None
    face_colors: np.ndarray | None = None

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices_m, dtype=np.float64)
        f = np.asarray(self.faces)
        where = f"CAD model '{self.name}'" + (f" ({self.source})" if self.source is not None else "")
        if v.ndim != 2 or v.shape[1] != 3 or not np.all(np.isfinite(v)):
            raise InputError(f"{where}: vertices_m must be a finite (V, 3) array, got shape {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
            raise InputError(f"{where}: faces must be an integer (F, 3) array, got {f.dtype} {f.shape}")
        if len(f) == 0:
            raise InputError(f"{where}: the mesh has no faces; a CAD model needs at least one triangle")
        if f.min() < 0 or f.max() >= len(v):
            raise InputError(f"{where}: face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
        if self.unit not in UNIT_TO_M:
            raise InputError(f"{where}: unknown unit {self.unit!r}; allowed: {', '.join(UNIT_TO_M)}")
        labels = np.zeros(len(f), np.int32) if self.part_labels is None else np.asarray(self.part_labels)
        names = tuple(self.part_names) or (self.name,)
        if labels.shape != (len(f),) or labels.min() < 0 or labels.max() >= len(names):
            raise InputError(f"{where}: part_labels must be ({len(f)},) ints in [0, {len(names)})")
        object.__setattr__(self, "vertices_m", _frozen(v))
        object.__setattr__(self, "faces", _frozen(f.astype(np.int64)))
        object.__setattr__(self, "part_labels", _frozen(labels.astype(np.int32)))
        object.__setattr__(self, "part_names", names)
        object.__setattr__(self, "class_name", self.class_name or self.name)
        object.__setattr__(self, "source", None if self.source is None else Path(self.source))
        object.__setattr__(self, "vertex_colors", _check_colors(self.vertex_colors, len(v), "vertex_colors"))
        object.__setattr__(self, "face_colors", _check_colors(self.face_colors, len(f), "face_colors"))

    @property
    def n_parts(self) -> int:
        """Number of parts ``P``."""
        return len(self.part_names)

    @cached_property
    def _used_vertices(self) -> np.ndarray:
        return self.vertices_m[np.unique(self.faces)]

    @cached_property
    def bbox_min(self) -> np.ndarray:
        """(3,) lower corner of the axis-aligned bounding box of the faces' vertices, metres."""
        return _frozen(self._used_vertices.min(axis=0))

    @cached_property
    def bbox_max(self) -> np.ndarray:
        """(3,) upper corner of the axis-aligned bounding box, metres."""
        return _frozen(self._used_vertices.max(axis=0))

    @property
    def extent(self) -> np.ndarray:
        """(3,) bounding-box size along x, y, z in metres."""
        return self.bbox_max - self.bbox_min

    @cached_property
    def diameter_m(self) -> float:
        """Largest distance between two vertices, metres (exact, via convex-hull vertices)."""
        return max_pairwise_distance(self._used_vertices)

    def part_faces(self, part: int | str) -> np.ndarray:
        """Indices (K,) of the faces of one part, given by index or name."""
        idx = self.part_names.index(part) if isinstance(part, str) else int(part)
        return np.flatnonzero(self.part_labels == idx)

    def to_trimesh(self, *, visuals: bool = True) -> trimesh.Trimesh:
        """A ``trimesh.Trimesh`` in metres (``process=False``), with colours when the model has them."""
        kwargs = {}
        if visuals and self.vertex_colors is not None:
            kwargs["vertex_colors"] = self.vertex_colors.copy()
        elif visuals and self.face_colors is not None:
            kwargs["face_colors"] = self.face_colors.copy()
        return trimesh.Trimesh(self.vertices_m.copy(), self.faces.copy(), process=False, **kwargs)

    def vertex_colors_or_default(self) -> np.ndarray | None:
        """(V, 4) uint8 colours per vertex (face colours averaged onto vertices), or ``None``."""
        if self.vertex_colors is not None:
            return self.vertex_colors
        if self.face_colors is None:
            return None
        return np.asarray(self.to_trimesh().visual.vertex_colors, dtype=np.uint8)

    def scaled(self, factors: float | tuple[float, float, float]) -> CadModel:
        """A copy scaled about the model origin by a uniform or per-axis factor (e.g. SDF ``<scale>``).

        A mirroring scale (odd number of negative factors) flips face winding so
        normals keep pointing outwards. Symmetries are dropped unless the scale
        is uniform, as a non-uniform scale breaks them in general.
        """
        s = np.broadcast_to(np.asarray(factors, dtype=np.float64), (3,))
        if not np.all(np.isfinite(s)) or np.any(s == 0):
            raise InputError(f"scale factors must be finite and non-zero, got {s.tolist()}")
        faces = self.faces[:, ::-1] if np.prod(s) < 0 else self.faces
        sym = self.symmetry if np.allclose(s, s[0]) and s[0] > 0 else Symmetry.none()
        if sym.kind != "none" and s[0] != 1.0:
            sym = _scale_symmetry(sym, float(s[0]))
        return CadModel(self.name, self.vertices_m * s, faces, self.unit, self.source, self.part_labels,
                        self.part_names, self.class_name, sym, self.vertex_colors, self.face_colors)


def _scale_symmetry(sym: Symmetry, s: float) -> Symmetry:
    """The same symmetry after scaling the model uniformly by ``s`` > 0 about its origin."""
    disc = []
    for T in sym.discrete:
        T2 = T.copy()
        T2[:3, 3] *= s
        disc.append(T2)
    offset = None if sym.offset_m is None else sym.offset_m * s
    return Symmetry(sym.kind, tuple(disc), sym.axis, offset)

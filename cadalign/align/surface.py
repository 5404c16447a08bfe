"""The CAD side of the registration: area-weighted surface samples of posed parts, with a KD-tree."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from cadalign.cad import CadModel
from cadalign.errors import InputError
from cadalign.raycast.core import MeshQuery
from cadalign.types import Rigid3

CadPart = CadModel | tuple[CadModel, Rigid3]
"""A CAD part: a model already in world metres, or a model and its ``world_from_part`` pose."""


@dataclass(frozen=True, eq=False)
class CadSurface:
    """Samples of a CAD structure's surface in world metres.

    Attributes:
        points_m: (M, 3) surface points, metres, world (CAD) frame.
        normals: (M, 3) unit normals of the faces the points lie on.
        part_index: (M,) index of the part each point lies on.
        part_names: (P,) part names.
        vertices_m: (V, 3) vertices of the posed parts as one mesh, metres, world frame.
        faces: (F, 3) its triangles.
    """

    points_m: np.ndarray
    normals: np.ndarray
    part_index: np.ndarray
    part_names: tuple[str, ...]
    vertices_m: np.ndarray
    faces: np.ndarray

    @cached_property
    def tree(self) -> cKDTree:
        """KD-tree of ``points_m``."""
        return cKDTree(self.points_m)

    @cached_property
    def centroid_m(self) -> np.ndarray:
        """(3,) mean of the samples (the area-weighted surface centroid), metres."""
        return self.points_m.mean(axis=0)

    @cached_property
    def diameter_m(self) -> float:
        """Diagonal of the axis-aligned bounding box, metres (cheap and within sqrt(3) of the true diameter)."""
        return float(np.linalg.norm(self.points_m.max(axis=0) - self.points_m.min(axis=0)))

    @cached_property
    def extent_m(self) -> float:
        """Largest side of the axis-aligned bounding box, metres."""
        return float(np.max(self.points_m.max(axis=0) - self.points_m.min(axis=0)))

    @cached_property
    def _mesh_query(self) -> MeshQuery:
        return MeshQuery(self.vertices_m, self.faces, origin=self.centroid_m)

    def distances(self, points_m: np.ndarray) -> np.ndarray:
        """(N,) exact distance of each point (N, 3) to the CAD triangles, metres (float32 precision,
        about 1e-7 of the distance from the CAD centroid)."""
        return self._mesh_query.distances(points_m)


def query_workers(n_queries: int) -> int:
    """Threads for a KD-tree query of ``n_queries`` points: below ~50k the thread start-up costs more."""
    return 1 if n_queries < 50_000 else -1


def _posed_mesh(part: CadPart, i: int) -> tuple[trimesh.Trimesh, str]:
    if isinstance(part, tuple):
        model, T = part
        if not isinstance(model, CadModel) or not isinstance(T, Rigid3):
            raise InputError(f"CAD part {i}: expected (CadModel, Rigid3), got ({type(model).__name__}, "
                             f"{type(T).__name__})")
        verts = T.apply(model.vertices_m)
    elif isinstance(part, CadModel):
        model, verts = part, np.asarray(part.vertices_m)
    else:
        raise InputError(f"CAD part {i}: expected a CadModel or (CadModel, Rigid3), got {type(part).__name__}")
    return trimesh.Trimesh(verts, model.faces, process=False), model.name


def sample_surface(parts: Sequence[CadPart], n_samples: int, seed: int) -> CadSurface:
    """Sample ``n_samples`` points on the union of the posed parts, proportionally to area.

    Args:
        parts: the structure's parts (see :data:`CadPart`), metres.
        n_samples: number of samples M.
        seed: seed of the sampling.

    Raises:
        InputError: no parts, or parts with zero total area.
    """
    if len(parts) == 0:
        raise InputError("no CAD parts given; pass at least one CAD model of the structure")
    meshes, names = zip(*(_posed_mesh(p, i) for i, p in enumerate(parts)), strict=True)
    areas = np.array([m.area for m in meshes])
    if not np.isfinite(areas.sum()) or areas.sum() <= 0:
        raise InputError(f"the CAD parts {list(names)} have zero surface area; check the meshes")
    mesh = trimesh.util.concatenate(list(meshes))
    face_part = np.repeat(np.arange(len(meshes)), [len(m.faces) for m in meshes])
    points, face = trimesh.sample.sample_surface(mesh, int(n_samples), seed=seed)
    normals = np.asarray(mesh.face_normals)[face]
    return CadSurface(np.asarray(points, dtype=np.float64), normals, face_part[face], tuple(names),
                      np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))

"""Mesh cleaning that keeps track of which input face each output face came from.

Exported CAD meshes carry duplicated vertices (one per face corner, split at
normal or UV seams), repeated faces, zero-area slivers and stray vertices. These
break adjacency-based code (normals, sampling by area, ray casting) but fixing
them must not scramble per-face data: :func:`clean_mesh` reports the surviving
input faces so part labels and colours can follow. The cleaning is done in
numpy (pymeshlab filters do not expose a face correspondence); its edge
topology measures match pymeshlab's ``get_topological_measures``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from cadalign.cad.model import CadModel
from cadalign.errors import InputError

logger = logging.getLogger(__name__)

MAX_COORD_M = 1e15
"""Largest accepted |coordinate|, metres: far beyond any geo-referenced site, far below where areas overflow."""


@dataclass(frozen=True, eq=False)
class CleanReport:
    """What :func:`clean_mesh` changed, plus the index maps to carry per-element data.

    Each removed face is counted once, in the first category that applies
    (non-finite, degenerate, zero-area, duplicate).

    Attributes:
        vertices_in: input vertex count.
        faces_in: input face count.
        vertices_out: output vertex count.
        faces_out: output face count.
        merged_vertices: vertices merged into an equal or closer-than-tolerance one.
        unreferenced_vertices: vertices dropped because no surviving face uses them.
        nonfinite_faces: faces removed because a vertex is NaN/inf.
        degenerate_faces: faces removed because two corners are the same vertex (after merging).
        zero_area_faces: faces removed because their area is below tolerance (e.g. collinear corners).
        duplicate_faces: faces removed because another face has the same three vertices (any order).
        non_manifold_edges: edges of the output shared by more than two faces.
        boundary_edges: edges of the output used by exactly one face (open borders; 0 if watertight).
        kept_face_ids: (F_out,) int64 index of the input face each output face is.
        vertex_source: (V_out,) int64 index of the input vertex each output vertex copies.
    """

    vertices_in: int
    faces_in: int
    vertices_out: int
    faces_out: int
    merged_vertices: int
    unreferenced_vertices: int
    nonfinite_faces: int
    degenerate_faces: int
    zero_area_faces: int
    duplicate_faces: int
    non_manifold_edges: int
    boundary_edges: int
    kept_face_ids: np.ndarray
    vertex_source: np.ndarray

    @property
    def changed(self) -> bool:
        """Whether any vertex or face was removed or merged."""
        return self.vertices_out != self.vertices_in or self.faces_out != self.faces_in

    def summary(self) -> str:
        """One line listing the non-zero fixes and the topology counts."""
        fixes = {
            "merged vertices": self.merged_vertices,
            "unreferenced vertices": self.unreferenced_vertices,
            "faces with non-finite vertices": self.nonfinite_faces,
            "degenerate faces": self.degenerate_faces,
            "zero-area faces": self.zero_area_faces,
            "duplicate faces": self.duplicate_faces,
        }
        done = ", ".join(f"{n} {what}" for what, n in fixes.items() if n) or "nothing to fix"
        return (f"{done}; {self.vertices_in}->{self.vertices_out} vertices, {self.faces_in}->{self.faces_out} "
                f"faces; {self.non_manifold_edges} non-manifold and {self.boundary_edges} boundary edges")


def edge_topology(faces: np.ndarray) -> tuple[int, int]:
    """Count non-manifold edges (> 2 faces) and boundary edges (1 face) of a triangle mesh.

    Args:
        faces: (F, 3) vertex indices.

    Returns:
        (non_manifold_edges, boundary_edges).
    """
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return 0, 0
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts > 2).sum()), int((counts == 1).sum())


def _merge_map(v: np.ndarray, finite: np.ndarray, tol: float) -> np.ndarray:
    """(V,) index of the vertex each vertex merges into (the lowest index of its cluster)."""
    rep = np.arange(len(v))
    idx = np.flatnonzero(finite)
    if len(idx) < 2:
        return rep
    pts = v[idx]
    if tol > 0:
        pairs = cKDTree(pts).query_pairs(tol, output_type="ndarray")
        n = len(idx)
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, comp = connected_components(graph, directed=False)
    else:
        _, comp = np.unique(pts, axis=0, return_inverse=True)
        comp = comp.ravel()
    first = np.full(comp.max() + 1, len(idx), dtype=np.int64)
    np.minimum.at(first, comp, np.arange(len(idx)))
    rep[idx] = idx[first[comp]]
    return rep


def _triangle_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def _validate(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or not (f.size == 0 or np.issubdtype(f.dtype, np.integer)):
        raise InputError(f"faces must be an integer (F, 3) array, got {f.dtype} {f.shape}")
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise InputError(f"face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
    finite = v[np.isfinite(v)]
    if finite.size and np.abs(finite).max() > MAX_COORD_M:
        raise InputError(f"vertex coordinates reach {np.abs(finite).max():.3g} m, beyond any real object "
                         f"(limit {MAX_COORD_M:g} m, where areas and distances overflow); check the file's unit/export")
    return v, f


def clean_mesh(
    vertices: np.ndarray, faces: np.ndarray, *, merge_tol_m: float = 1e-6, area_tol_m2: float = 1e-12
) -> tuple[np.ndarray, np.ndarray, CleanReport]:
    """Merge close vertices, drop bad and duplicate faces and unreferenced vertices.

    Surviving faces keep their input order, so per-face data follows with
    ``data[report.kept_face_ids]`` and per-vertex data with
    ``data[report.vertex_source]``. Face orientation is not changed.

    Args:
        vertices: (V, 3) positions, metres.
        faces: (F, 3) vertex indices.
        merge_tol_m: vertices closer than this (metres) are merged (clusters are
            transitive); 0 merges exact duplicates only.
        area_tol_m2: faces with area <= this (m^2) are dropped.

    Returns:
        vertices (V', 3) float64, faces (F', 3) int64 and a :class:`CleanReport`.
    """
    v, f = _validate(vertices, faces)
    if merge_tol_m < 0 or area_tol_m2 < 0:
        raise InputError(f"tolerances must be >= 0, got merge_tol_m={merge_tol_m}, area_tol_m2={area_tol_m2}")
    finite = np.all(np.isfinite(v), axis=1)
    rep = _merge_map(v, finite, merge_tol_m)
    f = rep[f]
    keep = np.all(finite[f], axis=1)
    nonfinite = int((~keep).sum())
    degenerate_mask = keep & ((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0]))
    keep &= ~degenerate_mask
    zero_area_mask = keep.copy()
    zero_area_mask[keep] = _triangle_areas(v, f[keep]) <= area_tol_m2
    keep &= ~zero_area_mask
    ids = np.flatnonzero(keep)
    _, first = np.unique(np.sort(f[ids], axis=1), axis=0, return_index=True)
    kept = ids[np.sort(first)]
    used = np.unique(f[kept])
    new_index = np.full(len(v), -1, dtype=np.int64)
    new_index[used] = np.arange(len(used))
    f_out = new_index[f[kept]]
    n_reps = int((rep == np.arange(len(v))).sum())
    non_manifold, boundary = edge_topology(f_out)
    report = CleanReport(
        vertices_in=len(v), faces_in=len(f), vertices_out=len(used), faces_out=len(kept),
        merged_vertices=len(v) - n_reps, unreferenced_vertices=n_reps - len(used), nonfinite_faces=nonfinite,
        degenerate_faces=int(degenerate_mask.sum()), zero_area_faces=int(zero_area_mask.sum()),
        duplicate_faces=len(ids) - len(kept), non_manifold_edges=non_manifold, boundary_edges=boundary,
        kept_face_ids=kept.astype(np.int64), vertex_source=used.astype(np.int64),
    )
    return v[used], f_out, report


def clean_model(model: CadModel, *, merge_tol_m: float = 1e-6, area_tol_m2: float = 1e-12) -> tuple[
    CadModel, CleanReport
]:
    """Clean a model's mesh (see :func:`clean_mesh`), carrying part labels and colours along; logs the fixes.

    Raises:
        InputError: when no face survives (every triangle was degenerate).
    """
    v, f, rep = clean_mesh(model.vertices_m, model.faces, merge_tol_m=merge_tol_m, area_tol_m2=area_tol_m2)
    where = str(model.source) if model.source is not None else model.name
    if rep.faces_out == 0:
        raise InputError(f"CAD '{where}': all {rep.faces_in} faces are degenerate (zero area or repeated "
                         "vertices); check the export, e.g. that the unit/scale is not collapsing it")
    level = logging.INFO if rep.changed else logging.DEBUG
    logger.log(level, "cleaned CAD '%s': %s", where, rep.summary())
    if rep.non_manifold_edges:
        logger.warning(
            "CAD '%s' has %d non-manifold edges (shared by more than two faces): rendering and ray casting are "
            "fine, but inside/outside tests (SDF, watertightness) are unreliable. Repair it if those matter "
            "(MeshLab: Filters > Cleaning and Repairing > Repair non Manifold Edges).", where, rep.non_manifold_edges)
    vc = None if model.vertex_colors is None else model.vertex_colors[rep.vertex_source]
    fc = None if model.face_colors is None else model.face_colors[rep.kept_face_ids]
    cleaned = replace(model, vertices_m=v, faces=f, part_labels=model.part_labels[rep.kept_face_ids],
                      vertex_colors=vc, face_colors=fc)
    return cleaned, rep

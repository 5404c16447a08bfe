"""Load CAD files (OBJ, PLY, STL, GLB/GLTF, DAE, OFF; STEP and IGES) into a :class:`CadModel` in metres.

Multi-part files (scenes) are flattened with each node's transform applied;
every scene node becomes one part, so ``part_labels`` keep the file's parts.
STEP/IGES files are tessellated by OpenCASCADE (:mod:`cadalign.formats.step`): each named product of a
STEP assembly becomes a part, and the unit the file declares is the model's unit. For mesh files the
unit is taken from ``unit=`` when given, else detected with a plausibility rule for subsea hardware
(see :func:`~cadalign.cad.units.detect_unit`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from cadalign.cad.clean import clean_model
from cadalign.cad.model import CadModel
from cadalign.cad.symmetry import Symmetry
from cadalign.cad.units import check_unit, detect_unit, unit_from_metres_per_unit, unit_scale
from cadalign.errors import InputError
from cadalign.formats.step import BREP_SUFFIXES, TessellationConfig, read_brep

__all__ = ["SUPPORTED_EXTENSIONS", "check_unit", "load_cad", "read_cad_parts"]

logger = logging.getLogger(__name__)

SUPPORTED_EXTENSIONS = (".obj", ".ply", ".stl", ".glb", ".gltf", ".dae", ".off", *BREP_SUFFIXES)


@dataclass(frozen=True, eq=False)
class CadParts:
    """A flattened CAD scene in file units (before unit conversion and cleaning).

    Attributes:
        vertices: (V, 3) float64 positions in file units.
        faces: (F, 3) int64 vertex indices.
        part_labels: (F,) int32 part index per face.
        part_names: (P,) names of the scene nodes.
        vertex_colors: (V, 4) uint8 or ``None``.
        face_colors: (F, 4) uint8 or ``None``.
        declared_unit: unit declared by the file's metadata (COLLADA ``<unit>``, glTF, STEP, IGES), or ``None``.
        unit_is_declared: the declared unit is authoritative (STEP / IGES: B-rep files always carry one), so no
            size rule overrides it.
    """

    vertices: np.ndarray
    faces: np.ndarray
    part_labels: np.ndarray
    part_names: tuple[str, ...]
    vertex_colors: np.ndarray | None
    face_colors: np.ndarray | None
    declared_unit: str | None
    unit_is_declared: bool = False


def _check_path(path: Path) -> Path:
    if not path.exists():
        raise InputError(f"CAD file not found: '{path}' (resolved from {Path.cwd()}); check the path")
    if not path.is_file():
        raise InputError(f"CAD path '{path}' is not a file; pass the mesh file itself")
    if path.stat().st_size == 0:
        raise InputError(f"CAD file '{path}' is empty (0 bytes); the export or copy did not finish - re-export it")
    if path.suffix.lower() not in SUPPORTED_EXTENSIONS:
        raise InputError(f"CAD file '{path}' has unsupported extension '{path.suffix}'; supported: "
                         f"{', '.join(SUPPORTED_EXTENSIONS)}. Export it from the CAD tool as STEP, or convert it "
                         "(e.g. with MeshLab or Blender) to PLY or OBJ")
    return path


def _read_scene(path: Path) -> trimesh.Scene:
    try:
        return trimesh.load_scene(path, process=False)
    except ImportError as exc:
        raise InputError(f"cannot read CAD file '{path}': a reader dependency is missing ({exc}); "
                         "install pycollada for .dae files (pip install pycollada)") from exc
    except Exception as exc:  # trimesh raises many types for a corrupt file
        raise InputError(f"cannot read CAD file '{path}' as {path.suffix.lstrip('.').upper()}: "
                         f"{type(exc).__name__}: {exc}. Check that the file is complete and valid "
                         "(open it in MeshLab) or re-export it") from exc


def _declared_unit(scene: trimesh.Scene) -> str | None:
    units = scene.units
    if not units:
        return None
    try:
        return unit_from_metres_per_unit(trimesh.units.to_inch(units) * 0.0254)
    except (ValueError, KeyError):
        logger.debug("ignoring unparsable declared units %r", units)
        return None


def _node_colors(mesh: trimesh.Trimesh) -> tuple[str, np.ndarray] | None:
    """('vertex', (V, 4)) or ('face', (F, 4)) uint8 colours of one mesh, or None if it has none."""
    vis = mesh.visual
    if vis.kind == "texture":
        vis = vis.to_color()  # samples the texture (or the material colour) at each vertex
    for kind, n in (("vertex", len(mesh.vertices)), ("face", len(mesh.faces))):
        if vis.kind != kind:
            continue
        c = np.asarray(vis.vertex_colors if kind == "vertex" else vis.face_colors, dtype=np.uint8)
        if c.ndim == 1:  # one colour for the whole mesh (an untextured material)
            c = np.tile(c, (n, 1))
        if c.shape[0] != n or c.shape[1] not in (3, 4):
            logger.debug("ignoring %s colours of shape %s for %d elements", kind, c.shape, n)
            return None
        if c.shape[1] == 3:
            c = np.concatenate([c, np.full((n, 1), 255, np.uint8)], axis=1)
        return kind, c
    return None


def _merge_colors(meshes: list[trimesh.Trimesh], colors: list[tuple[str, np.ndarray] | None]) -> tuple[
    np.ndarray | None, np.ndarray | None
]:
    """Combine per-part colours: per-vertex if any part has them, else per-face, else none."""
    kinds = {c[0] for c in colors if c is not None}
    if not kinds:
        return None, None
    default = np.asarray(trimesh.visual.DEFAULT_COLOR, dtype=np.uint8)
    if "vertex" in kinds:
        out = []
        for m, c in zip(meshes, colors, strict=True):
            if c is None:
                out.append(np.tile(default, (len(m.vertices), 1)))
            elif c[0] == "face":
                out.append(np.asarray(trimesh.visual.ColorVisuals(m, face_colors=c[1]).vertex_colors, np.uint8))
            else:
                out.append(c[1])
        return np.concatenate(out), None
    out = [np.tile(default, (len(m.faces), 1)) if c is None else c[1] for m, c in zip(meshes, colors, strict=True)]
    return None, np.concatenate(out)


def _ordered_nodes(scene: trimesh.Scene) -> list[str]:
    """Geometry nodes in file order of their geometry, then by name, so part ids are stable."""
    rank = {name: i for i, name in enumerate(scene.geometry)}
    return sorted(scene.graph.nodes_geometry, key=lambda n: (rank.get(scene.graph[n][1], len(rank)), str(n)))


def _read_brep_parts(path: Path, tessellation: TessellationConfig | None) -> CadParts:
    """A STEP/IGES file's tessellation as :class:`CadParts` in its declared unit."""
    brep = read_brep(path, tessellation)
    unit = unit_from_metres_per_unit(brep.metres_per_unit)
    if unit is None:  # e.g. feet: OpenCASCADE converted the coordinates already; keep them in metres
        logger.warning("CAD '%s' declares a unit of %g m, which cadalign does not name; it is read as metres "
                       "(converted by OpenCASCADE) and recorded as 'm'", path.name, brep.metres_per_unit)
        unit, brep_scale = "m", 1.0
    else:
        brep_scale = brep.metres_per_unit
    return CadParts(brep.vertices_m / brep_scale, brep.faces, brep.part_labels, brep.part_names, None, None, unit,
                    unit_is_declared=True)


def read_cad_parts(path: str | Path, tessellation: TessellationConfig | None = None) -> CadParts:
    """Read a CAD file and flatten its scene graph, in file units, without cleaning.

    Every scene node holding a triangle mesh becomes a part; its node
    transform is applied (mirroring transforms flip the winding back). Nodes
    holding points or lines are skipped.

    Args:
        path: the mesh file, or a STEP/IGES file (tessellated per ``tessellation``, default
            :class:`~cadalign.formats.step.TessellationConfig`).

    Returns:
        the flattened :class:`CadParts`.

    Raises:
        InputError: missing file, unsupported extension, unreadable file, or no triangle at all.
    """
    path = _check_path(Path(path))
    if path.suffix.lower() in BREP_SUFFIXES:
        return _read_brep_parts(path, tessellation)
    scene = _read_scene(path)
    meshes, names, verts, faces, labels, colors = [], [], [], [], [], []
    offset = 0
    for node in _ordered_nodes(scene):
        T, geom_name = scene.graph[node]
        mesh = scene.geometry.get(geom_name)
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            logger.debug("CAD '%s': skipping node %r (no triangles)", path.name, node)
            continue
        T = np.asarray(T, dtype=np.float64)
        f = np.asarray(mesh.faces, dtype=np.int64)
        v = np.asarray(mesh.vertices, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise InputError(f"CAD file '{path}' is corrupt: part {node!r} has vertices of shape {v.shape} and "
                             f"faces of shape {f.shape} instead of (V, 3) and (F, 3); re-export it")
        if f.min() < 0 or f.max() >= len(mesh.vertices):
            raise InputError(f"CAD file '{path}' is corrupt: part {node!r} has faces referring to vertex "
                             f"{int(f.max()) if f.max() >= len(mesh.vertices) else int(f.min())} of "
                             f"{len(mesh.vertices)}; re-export it")
        if not np.all(np.isfinite(T)):
            raise InputError(f"CAD file '{path}' is corrupt: part {node!r} has a non-finite transform; re-export it")
        if np.linalg.det(T[:3, :3]) < 0:
            f = f[:, ::-1]
        with np.errstate(invalid="ignore", over="ignore"):  # NaN/huge vertices are refused or dropped later
            verts.append(v @ T[:3, :3].T + T[:3, 3])
        faces.append(f + offset)
        labels.append(np.full(len(f), len(names), dtype=np.int32))
        colors.append(_node_colors(mesh))
        meshes.append(mesh)
        names.append(str(node))
        offset += len(mesh.vertices)
    if not faces:
        raise InputError(f"CAD file '{path}' has no triangle faces (it may hold only points, lines or an empty "
                         f"scene, or not be a valid {path.suffix.lstrip('.').upper()} file); export the object as "
                         "a surface mesh")
    vc, fc = _merge_colors(meshes, colors)
    return CadParts(np.concatenate(verts), np.concatenate(faces), np.concatenate(labels), tuple(names), vc, fc,
                    _declared_unit(scene))


def select_part(parts: CadParts, name: str, path: Path) -> CadParts:
    """Only the faces of part ``name`` (vertices unchanged; unused ones are dropped by cleaning).

    Raises:
        InputError: no part of that name, naming the file's parts.
    """
    if name not in parts.part_names:
        raise InputError(f"CAD file '{path}' has no part named {name!r}; its parts: {', '.join(parts.part_names)} "
                         f"(refer to one as \"{path.name}#NAME\")")
    keep = parts.part_labels == parts.part_names.index(name)
    used, faces = np.unique(parts.faces[keep], return_inverse=True)
    vc = parts.vertex_colors[used] if parts.vertex_colors is not None else None
    fc = parts.face_colors[keep] if parts.face_colors is not None else None
    return CadParts(parts.vertices[used], faces.reshape(-1, 3), np.zeros(int(keep.sum()), np.int32), (name,),
                    vc, fc, parts.declared_unit, parts.unit_is_declared)


def _resolve_unit(parts: CadParts, unit: str | None, source: str) -> str:
    if unit is not None:
        unit_scale(unit)  # validates the code
        return unit
    if parts.unit_is_declared and parts.declared_unit is not None:
        return parts.declared_unit
    used = parts.vertices[np.unique(parts.faces)]
    if not np.all(np.isfinite(used)):
        raise InputError(f"CAD file '{source}' has non-finite (NaN/inf) vertex coordinates; re-export it")
    largest = float((used.max(axis=0) - used.min(axis=0)).max())
    return detect_unit(largest, source, parts.declared_unit)


def load_cad(
    path: str | Path,
    unit: str | None = None,
    *,
    name: str | None = None,
    class_name: str | None = None,
    symmetry: Symmetry | str | None = None,
    clean: bool = True,
    merge_tol_m: float = 1e-6,
    part: str | None = None,
    tessellation: TessellationConfig | None = None,
) -> CadModel:
    """Load a CAD mesh file as a :class:`CadModel` in metres.

    Args:
        path: OBJ, PLY, STL, GLB, GLTF, DAE, OFF, STEP (.step/.stp) or IGES (.iges/.igs) file.
        unit: the file's unit (``m``, ``cm``, ``mm``, ``in``). ``None`` detects it:
            STEP/IGES: the unit the file declares; meshes: the unit the file declares if
            plausible, else metres, or millimetres when the object would be > 50 m across
            (logged as a WARNING).
        name: model name; defaults to the file stem.
        class_name: semantic class; defaults to ``name``.
        symmetry: a :class:`Symmetry` or a name such as ``continuous_z``; default none.
        clean: merge duplicate vertices and drop degenerate/duplicate faces (see
            :func:`~cadalign.cad.clean.clean_mesh`); part labels follow.
        merge_tol_m: vertex merge distance in metres when cleaning.
        part: keep only this named part of the file (a STEP product such as ``valve_1``, a scene node); its
            vertices stay in the file's frame. ``None`` keeps every part.
        tessellation: how finely STEP/IGES surfaces are triangulated (ignored for meshes).

    Returns:
        the model; ``model.unit`` records the source unit.

    Raises:
        InputError: missing file, unsupported extension, unreadable or empty mesh.
        UnitError: unknown ``unit``, or a size implausible in every unit.
    """
    path = Path(path)
    parts = read_cad_parts(path, tessellation)
    if part is not None:
        parts = select_part(parts, part, path)
    resolved = _resolve_unit(parts, unit, path.name)
    if isinstance(symmetry, str):
        symmetry = Symmetry.from_name(symmetry)
    model = CadModel(
        name=name or path.stem, vertices_m=parts.vertices * unit_scale(resolved), faces=parts.faces,
        unit=resolved, source=path, part_labels=parts.part_labels, part_names=parts.part_names,
        class_name=class_name or "", symmetry=symmetry or Symmetry.none(),
        vertex_colors=parts.vertex_colors, face_colors=parts.face_colors,
    )
    if clean:
        model, _ = clean_model(model, merge_tol_m=merge_tol_m)
    logger.debug("loaded CAD '%s' (%s): %d vertices, %d faces, %d parts, extent %s m", path.name, resolved,
                 len(model.vertices_m), len(model.faces), model.n_parts, np.round(model.extent, 4).tolist())
    return model

"""BOP ``models/`` output: ``models_info.json`` entries and ``obj_XXXXXX.ply`` meshes, in millimetres.

BOP (https://github.com/thodan/bop_toolkit, docs/bop_datasets_format.md) stores
model geometry, sizes, diameters and symmetry translations in millimetres.
cadalign works in metres; this module is the one place where CAD models are
converted to mm.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from cadalign.cad.model import CadModel
from cadalign.cad.symmetry import Symmetry
from cadalign.errors import InputError
from cadalign.io import atomic_path

logger = logging.getLogger(__name__)

M_TO_MM = 1000.0


def _round(x: float, ndigits: int = 9) -> float:
    # round away float noise from m->mm products (0.1 * 1000 = 100.00000000000001)
    return round(float(x), ndigits)


def models_info_entry(model: CadModel) -> dict:
    """The BOP ``models_info.json`` entry of one model (all lengths in millimetres).

    Keys: ``diameter``, ``min_x/y/z``, ``size_x/y/z``, and when the model is
    symmetric ``symmetries_discrete`` (list of flattened row-major 4x4 matrices,
    translation in mm) and/or ``symmetries_continuous`` (list of
    ``{"axis": [3], "offset": [3] mm}``).

    Args:
        model: the model (metres).

    Returns:
        a JSON-serialisable dict.
    """
    entry: dict = {"diameter": _round(model.diameter_m * M_TO_MM)}
    for i, ax in enumerate("xyz"):
        entry[f"min_{ax}"] = _round(model.bbox_min[i] * M_TO_MM)
        entry[f"size_{ax}"] = _round(model.extent[i] * M_TO_MM)
    sym = model.symmetry
    if sym.discrete:
        mats = []
        for T in sym.discrete:
            T_mm = T.copy()
            T_mm[:3, 3] *= M_TO_MM
            mats.append([_round(v) for v in T_mm.ravel()])
        entry["symmetries_discrete"] = mats
    if sym.kind == "continuous":
        assert sym.axis is not None and sym.offset_m is not None
        entry["symmetries_continuous"] = [
            {"axis": [_round(v) for v in sym.axis], "offset": [_round(v * M_TO_MM) for v in sym.offset_m]}
        ]
    return entry


def symmetry_from_entry(entry: dict) -> Symmetry:
    """The :class:`Symmetry` (metres) of one ``models_info.json`` entry (millimetres): the inverse of the
    symmetry part of :func:`models_info_entry`. Only the first continuous symmetry is kept (one axis)."""
    mats = []
    for flat in entry.get("symmetries_discrete", []):
        T = np.reshape(np.asarray(flat, dtype=np.float64), (4, 4)).copy()
        T[:3, 3] /= M_TO_MM
        mats.append(T)
    cont = entry.get("symmetries_continuous", [])
    if cont:
        c = cont[0]
        return Symmetry("continuous", tuple(mats), np.asarray(c["axis"], float),
                        np.asarray(c.get("offset", [0.0, 0.0, 0.0]), float) / M_TO_MM)
    return Symmetry.discrete_from(mats) if mats else Symmetry.none()


def write_models_info(models: dict[int, CadModel], path: str | Path) -> Path:
    """Write BOP ``models_info.json`` for ``{obj_id: model}`` atomically (temp file + ``os.replace``).

    Args:
        models: BOP object ids (>= 1) to models.
        path: the JSON file to write.

    Returns:
        ``path``.
    """
    bad = [k for k in models if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1]
    if bad:
        raise InputError(f"BOP object ids must be integers >= 1, got {bad} (writing {path})")
    info = {str(int(k)): models_info_entry(models[k]) for k in sorted(models)}
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(info, indent=2) + "\n", encoding="utf-8")
    logger.info("wrote BOP models_info for %d models to %s", len(info), path)
    return path


def _ply_header(n_v: int, n_f: int, colors: bool, name: str) -> bytes:
    lines = ["ply", "format binary_little_endian 1.0", f"comment cadalign model '{name}', units: mm",
             f"element vertex {n_v}"]
    lines += [f"property float {p}" for p in ("x", "y", "z", "nx", "ny", "nz")]
    if colors:
        lines += [f"property uchar {c}" for c in ("red", "green", "blue")]
    lines += [f"element face {n_f}", "property list uchar int vertex_indices", "end_header"]
    return ("\n".join(lines) + "\n").encode("ascii")


def write_model_ply_mm(model: CadModel, path: str | Path) -> Path:
    """Write a model as a BOP ``models/obj_XXXXXX.ply``: binary PLY in millimetres, with vertex normals.

    Vertex colours (``red green blue``) are written when the model has vertex or
    face colours. The write is atomic.

    Args:
        model: the model (metres).
        path: the PLY file to write.

    Returns:
        ``path``.
    """
    mesh = model.to_trimesh(visuals=False)
    colors = model.vertex_colors_or_default()
    vdt = [(c, "<f4") for c in ("x", "y", "z", "nx", "ny", "nz")]
    if colors is not None:
        vdt += [(c, "u1") for c in ("red", "green", "blue")]
    verts = np.empty(len(model.vertices_m), dtype=vdt)
    for i, c in enumerate("xyz"):
        verts[c] = model.vertices_m[:, i] * M_TO_MM
        verts[f"n{c}"] = mesh.vertex_normals[:, i]
    if colors is not None:
        for i, c in enumerate(("red", "green", "blue")):
            verts[c] = colors[:, i]
    faces = np.empty(len(model.faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    faces["n"] = 3
    faces["v"] = model.faces
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(_ply_header(len(verts), len(faces), colors is not None, model.name)
                        + verts.tobytes() + faces.tobytes())
    return path

"""Map files (re-open and extend), labelled mesh / point cloud PLY files.

A map file is one ``.npz``: the map's arrays (TSDF voxel blocks or surfels) plus a JSON ``meta`` entry with
the method, the resolved :class:`~cadalign.fuse.config.FuseConfig`, the class names, the float64 local
origin and the ids of the frames already integrated; :func:`load_map` rebuilds the same map, ready for more
``integrate`` calls.

PLY files are binary little-endian with per-vertex ``x y z`` (double, world metres), ``nx ny nz`` (float),
``red green blue`` (uchar, observed colour), ``class`` (ushort, fused label) and ``confidence`` (float, the
fused probability of that label); meshes add ``face`` lists.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cadalign._version import __version__
from cadalign.config import from_dict, to_dict
from cadalign.errors import InputError
from cadalign.fuse.base import LabelledGeometry
from cadalign.fuse.config import FuseConfig
from cadalign.fuse.surfel import SurfelMap
from cadalign.fuse.tsdf import SemanticTSDF
from cadalign.io import atomic_path

MAP_FORMAT = 1


@dataclass
class MapMeta:
    """What a map file records beside the arrays."""

    class_names: tuple[str, ...]
    frame_ids: list[int] = field(default_factory=list)
    """Ids of the frames integrated so far (in order)."""
    source: str = ""
    """The scene the frames came from."""


def new_map(cfg: FuseConfig, n_classes: int, origin: np.ndarray | None = None) -> SemanticTSDF | SurfelMap:
    """An empty map of ``cfg.method``."""
    cls = SemanticTSDF if cfg.method == "tsdf" else SurfelMap
    return cls(cfg, n_classes, origin)


def save_map(m: SemanticTSDF | SurfelMap, meta: MapMeta, path: Path) -> Path:
    """Write the map and ``meta`` to ``path`` (.npz) atomically."""
    record = {
        "format": MAP_FORMAT, "version": __version__, "method": m.cfg.method, "config": to_dict(m.cfg),
        "n_classes": m.n_classes, "origin": None if m.origin is None else [float(x) for x in m.origin],
        "frames_integrated": m.frames_integrated, "class_names": list(meta.class_names),
        "frame_ids": [int(i) for i in meta.frame_ids], "source": meta.source,
    }
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, meta=np.frombuffer(json.dumps(record).encode(), dtype=np.uint8), **m.state())
    return Path(path)


def load_map(path: Path) -> tuple[SemanticTSDF | SurfelMap, MapMeta]:
    """Re-open a map written by :func:`save_map` (ready to integrate more frames)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"map file not found: {path}")
    try:
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        record = json.loads(arrays.pop("meta").tobytes().decode())
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"{path} is not a cadalign map file ({exc}); re-run `cadalign fuse`") from exc
    if record.get("format") != MAP_FORMAT:
        raise InputError(f"{path}: map format {record.get('format')} is not supported (expected {MAP_FORMAT})")
    cfg = from_dict(FuseConfig, record["config"], source=str(path))
    origin = None if record["origin"] is None else np.asarray(record["origin"], dtype=np.float64)
    m = new_map(cfg, int(record["n_classes"]), origin)
    m.load_state(arrays)
    m.frames_integrated = int(record["frames_integrated"])
    return m, MapMeta(tuple(record["class_names"]), list(record["frame_ids"]), record.get("source", ""))


def write_ply(geom: LabelledGeometry, path: Path) -> Path:
    """Write a labelled mesh (``geom.faces`` set) or point cloud as binary PLY (see the module docstring)."""
    n = len(geom)
    vert = np.empty(n, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("nx", "<f4"), ("ny", "<f4"),
                              ("nz", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("class", "<u2"),
                              ("confidence", "<f4")])
    for i, k in enumerate("xyz"):
        vert[k] = geom.points_m[:, i]
        vert["n" + k] = geom.normals[:, i]
    for i, k in enumerate(("red", "green", "blue")):
        vert[k] = geom.colors[:, i]
    vert["class"] = geom.labels
    vert["confidence"] = geom.probs[np.arange(n), geom.labels] if n else []
    header = ["ply", "format binary_little_endian 1.0", f"comment cadalign {__version__} labelled map",
              f"element vertex {n}"]
    header += [f"property {t} {name}" for name, t in (
        ("x", "double"), ("y", "double"), ("z", "double"), ("nx", "float"), ("ny", "float"), ("nz", "float"),
        ("red", "uchar"), ("green", "uchar"), ("blue", "uchar"), ("class", "ushort"), ("confidence", "float"))]
    faces = geom.faces
    if faces is not None:
        header += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header.append("end_header")
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vert.tobytes())
        if faces is not None:
            f = np.empty(len(faces), dtype=[("n", "u1"), ("v", "<i4", (3,))])
            f["n"], f["v"] = 3, faces
            fh.write(f.tobytes())
    return Path(path)


def read_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PLY written by :func:`write_ply`: the vertex record array and the (F, 3) faces (or None)."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path} is not a PLY file")
    lines = data[:end].decode("ascii").splitlines()
    types = {"double": "<f8", "float": "<f4", "uchar": "u1", "ushort": "<u2", "int": "<i4"}
    n_vert = n_face = 0
    props: list[tuple[str, str]] = []
    for line in lines:
        parts = line.split()
        if parts[:2] == ["element", "vertex"]:
            n_vert = int(parts[2])
        elif parts[:2] == ["element", "face"]:
            n_face = int(parts[2])
        elif parts[0] == "property" and parts[1] != "list":
            props.append((parts[2], types[parts[1]]))
    body = data[end + len(b"end_header\n"):]
    vert = np.frombuffer(body, dtype=props, count=n_vert)
    if not n_face:
        return vert, None
    faces = np.frombuffer(body, dtype=[("n", "u1"), ("v", "<i4", (3,))], count=n_face, offset=vert.nbytes)
    return vert, faces["v"].astype(np.int64)

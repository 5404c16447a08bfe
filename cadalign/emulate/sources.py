"""Load a SOURCE to emulate sensors in: a CAD scene, a mesh PLY with layers, or one image + depth.

- a scene spec (``.toml``/``.yaml``): every object's CAD mesh posed in the world, class from the spec, part
  id = instance id (object ``k`` -> ``k + 1``, seabed 0), colour = the main colour of its material;
- a mesh ``.ply`` (binary or ASCII): e.g. a fused map or a layered mesh written by ``cadalign emulate mesh``;
  per-vertex ``red/green/blue`` and per-vertex or per-face ``class``/``class_id``/``label``, ``part``/``part_id``/
  ``instance`` and ``pane``/``pane_id`` properties are used when present; metres unless a unit is given;
- any other CAD file :func:`cadalign.cad.load.load_cad` reads (OBJ, STL, GLB/GLTF, DAE, OFF, STEP/IGES), in the
  unit given or the one it detects: class 0, part = the file's part + 1, colour from the file (grey without);
- one image: an RGB frame of a BOP scene folder (``.../rgb/000000.png``; depth, class and instance maps and
  K are read beside it) or an ``.npz`` with ``rgb``, ``depth_m``, ``K`` and optional ``class_id``,
  ``part_id``, ``pane_mask`` -> a layered mesh (:mod:`cadalign.emulate.layered_mesh`) in the camera frame.

PLY writing for :class:`LayeredMesh` lives here too, so written meshes load back unchanged.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from cadalign.cad.load import SUPPORTED_EXTENSIONS, load_cad
from cadalign.cad.units import unit_scale
from cadalign.emulate.layered_mesh import PRESETS, ImageInput, mesh_from_image
from cadalign.emulate.mesh import LayeredMesh, concatenate
from cadalign.errors import InputError
from cadalign.formats.bop import BopScene
from cadalign.io import atomic_path, read_image
from cadalign.sim.textures import BASE_COLOURS
from cadalign.types import Camera

log = logging.getLogger(__name__)
SCENE_SUFFIXES = (".toml", ".yaml", ".yml")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".npz")
MESH_SUFFIXES = SUPPORTED_EXTENSIONS
"""Mesh and CAD files: ``.ply`` by :func:`ply_mesh` (layers kept), the others by :func:`cad_mesh`."""
_CLASS_KEYS = ("class", "class_id", "label")
_PART_KEYS = ("part", "part_id", "instance")
_PANE_KEYS = ("pane", "pane_id")


def scene_mesh(path: Path) -> LayeredMesh:
    """The CAD scene of a scene spec as one layered mesh in the world frame."""
    from cadalign.sim.scene import build_scene  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.sim.spec import load_scene  # lazy: pulls cv2; keeps `cadalign --help` light

    spec = load_scene(Path(path))
    scene = build_scene(spec, Path(path), width=8, height=8)

    def part(vertices: np.ndarray, faces: np.ndarray, texture: str, class_id: int, part_id: int) -> LayeredMesh:
        n = len(faces)
        rgb = np.rint(np.asarray(BASE_COLOURS[texture][0]) * 255).astype(np.uint8)
        return LayeredMesh(vertices, faces, np.tile(rgb, (n, 1)), np.full(n, class_id), np.full(n, part_id),
                           np.zeros(n), class_names=spec.classes)

    meshes = [part(o.T_world_from_obj.apply(o.mesh.vertices), o.mesh.faces, o.texture, o.class_id, k + 1)
              for k, o in enumerate(scene.objects)]
    if scene.seabed is not None:
        meshes.append(part(scene.seabed.vertices, scene.seabed.faces, spec.seabed.texture, 0, 0))
    return concatenate(meshes)


def _names(data: np.ndarray | dict | None) -> tuple[str, ...]:
    """Property names of a PLY element's data: a structured array (binary PLY) or a dict of arrays (ASCII PLY)."""
    if isinstance(data, dict):
        return tuple(data)
    return () if data is None or data.dtype.names is None else tuple(data.dtype.names)


def _field(data: np.ndarray | dict | None, keys: tuple[str, ...]) -> np.ndarray | None:
    names = _names(data)
    for k in keys:
        if k in names:
            return np.asarray(data[k])  # type: ignore[index]
    return None


def _face_layer(vdata, fdata, faces: np.ndarray, keys: tuple[str, ...]) -> np.ndarray:
    """A per-face layer from face properties, else from vertex properties (majority of the corners), else 0."""
    f = _field(fdata, keys)
    if f is not None:
        return f.astype(np.int32)
    v = _field(vdata, keys)
    if v is None:
        return np.zeros(len(faces), np.int32)
    a, b, c = v.astype(np.int32)[faces].T
    return np.where(b == c, b, a)


def ply_mesh(path: Path, unit: str | None = None) -> LayeredMesh:
    """A mesh PLY (binary or ASCII) with optional colour / class / part / pane properties per vertex or face;
    vertices in ``unit`` (``m``, ``cm``, ``mm``, ``in``; None: metres, as a layered mesh or a fused map is)."""

    path = Path(path)
    if not path.is_file():
        raise InputError(f"mesh not found: {path}")
    try:
        m = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise InputError(f"could not read mesh {path}: {exc}") from exc
    if len(m.faces) == 0:
        raise InputError(f"{path} has no faces; emulation needs a triangle mesh (not a point cloud)")
    raw = m.metadata.get("_ply_raw", {})
    vdata, fdata = raw.get("vertex", {}).get("data"), raw.get("face", {}).get("data")
    faces = np.asarray(m.faces, dtype=np.int64)
    vrgb = None
    if all(c in _names(vdata) for c in ("red", "green", "blue")):
        vrgb = np.stack([vdata[c] for c in ("red", "green", "blue")], 1).astype(np.uint8)
    if all(c in _names(fdata) for c in ("red", "green", "blue")):
        frgb = np.stack([fdata[c] for c in ("red", "green", "blue")], 1).astype(np.uint8)
    elif vrgb is not None:
        frgb = np.rint(vrgb[faces].astype(np.float64).mean(1)).astype(np.uint8)
    else:
        frgb = np.full((len(faces), 3), 180, np.uint8)
    scale = 1.0 if unit is None else unit_scale(unit)
    return LayeredMesh(np.asarray(m.vertices) * scale, faces, frgb, _face_layer(vdata, fdata, faces, _CLASS_KEYS),
                       _face_layer(vdata, fdata, faces, _PART_KEYS), _face_layer(vdata, fdata, faces, _PANE_KEYS),
                       vrgb)


def cad_mesh(path: Path, unit: str | None = None) -> LayeredMesh:
    """A CAD file read by :func:`cadalign.cad.load.load_cad` (in ``unit``, None: detected) as a layered mesh: class
    0, part = the file's part + 1, face colour from the file's face or vertex colours (grey without)."""

    model = load_cad(Path(path), unit=unit)
    faces = np.asarray(model.faces, dtype=np.int64)
    n = len(faces)
    vrgb = None if model.vertex_colors is None else np.asarray(model.vertex_colors)[:, :3].astype(np.uint8)
    if model.face_colors is not None:
        frgb = np.asarray(model.face_colors)[:, :3].astype(np.uint8)
    elif vrgb is not None:
        frgb = np.rint(vrgb[faces].astype(np.float64).mean(1)).astype(np.uint8)
    else:
        frgb = np.full((n, 3), 180, np.uint8)
    parts = np.zeros(n, np.int32) if model.part_labels is None else np.asarray(model.part_labels, np.int32)
    return LayeredMesh(np.asarray(model.vertices_m), faces, frgb, np.zeros(n, np.int32), parts + 1,
                       np.zeros(n, np.int32), vrgb)


def write_ply(mesh: LayeredMesh, path: Path) -> Path:
    """Binary PLY (float64 vertices, optional vertex colour, per-face colour/class/part/pane), atomically."""
    vt = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if mesh.vertex_rgb is not None:
        vt += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vd = np.zeros(len(mesh.vertices_m), dtype=vt)
    vd["x"], vd["y"], vd["z"] = mesh.vertices_m.T
    if mesh.vertex_rgb is not None:
        vd["red"], vd["green"], vd["blue"] = mesh.vertex_rgb.T
    ft = [("n", "u1"), ("vi", "<i4", (3,)), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
          ("class_id", "<i4"), ("part_id", "<i4"), ("pane_id", "<i4")]
    fd = np.zeros(mesh.n_faces, dtype=ft)
    fd["n"], fd["vi"] = 3, mesh.faces
    fd["red"], fd["green"], fd["blue"] = mesh.face_rgb.T
    fd["class_id"], fd["part_id"], fd["pane_id"] = mesh.class_id, mesh.part_id, mesh.pane_id
    vprops = "".join(f"property {'double' if t == '<f8' else 'uchar'} {n}\n" for n, t in vt)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment cadalign layered mesh (metres)\n"
        + "".join(f"comment class {i} {n}\n" for i, n in enumerate(mesh.class_names))
        + f"element vertex {len(vd)}\n{vprops}element face {len(fd)}\nproperty list uchar int vertex_indices\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty int class_id\n"
        "property int part_id\nproperty int pane_id\nend_header\n"
    )
    with atomic_path(Path(path)) as tmp:
        tmp.write_bytes(header.encode("ascii") + vd.tobytes() + fd.tobytes())
    return Path(path)


def image_scene_dir(path: Path) -> Path | None:
    """The BOP scene folder of an image source ``SCENE/rgb/NNNNNN.png``; None for an ``.npz``.

    Raises:
        InputError: neither an ``.npz`` nor an RGB frame of a BOP scene folder.
    """
    path = Path(path)
    if path.suffix.lower() == ".npz":
        return None
    scene_dir = path.parent.parent
    if path.parent.name != "rgb" or not (scene_dir / "scene_camera.json").is_file():
        raise InputError(f"{path}: an image source must be an RGB frame of a BOP scene folder "
                         "(SCENE/rgb/NNNNNN.png with depth/ and scene_camera.json beside it) or an .npz")
    return scene_dir


def read_image_input(path: Path) -> ImageInput:
    """An RGB-D frame from an ``.npz`` or from an RGB image inside a BOP scene folder (``rgb/NNNNNN.png``)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"image source not found: {path}")
    scene_dir = image_scene_dir(path)
    if scene_dir is None:
        with np.load(path) as z:
            missing = [k for k in ("rgb", "depth_m", "K") if k not in z.files]
            if missing:
                raise InputError(f"{path} lacks {missing}; an image source .npz needs rgb, depth_m and K")
            opt = {k: z[k] for k in ("class_id", "part_id", "pane_mask", "T_world_from_cam") if k in z.files}
            if "class_names" in z.files:
                opt["class_names"] = tuple(str(n) for n in z["class_names"])
            return ImageInput(z["rgb"], z["depth_m"], z["K"], **opt)

    bop = BopScene(scene_dir)
    im_id = int(path.stem)
    frame = bop.frame(im_id)
    extra = {}
    for key, folder in (("class_id", "class"), ("part_id", "instance")):
        p = scene_dir / folder / path.name
        if p.is_file():
            extra[key] = read_image(p, unchanged=True).astype(np.int32)
    T = None if frame.T_cam_from_world is None else frame.T_cam_from_world.inverse().matrix()
    return ImageInput(bop.rgb(im_id), bop.depth_m(im_id), frame.camera.K, T_world_from_cam=T, **extra)


DepthFn = Callable[[np.ndarray, Camera], np.ndarray]
"""``(rgb (H, W, 3) uint8, camera) -> (H, W)`` metric z-depth, e.g. :func:`cadalign.fuse.predictors.depth_predictor`."""
SegFn = Callable[[np.ndarray], np.ndarray]
"""``rgb -> (C, H, W)`` class probabilities, e.g. :func:`cadalign.fuse.predictors.seg_predictor`."""


def with_predictions(inp: ImageInput, depth_fn: DepthFn | None = None, seg_fn: SegFn | None = None) -> ImageInput:
    """The image input with its depth and/or class map replaced by network predictions (GT kept otherwise).

    This is how a layered mesh is built from a single image in the field, where no ground truth exists.
    """
    rgb = np.asarray(inp.rgb)
    H, W = rgb.shape[:2]
    depth, cls = inp.depth_m, inp.class_id
    if depth_fn is not None:
        depth = np.asarray(depth_fn(rgb, Camera(inp.K, W, H)), dtype=np.float64)
    if seg_fn is not None:
        prob = np.asarray(seg_fn(rgb))
        if prob.ndim != 3 or prob.shape[1:] != (H, W):
            raise InputError(f"the segmentation predictor returned {prob.shape}; expected (C, {H}, {W})")
        cls = prob.argmax(0).astype(np.int32)
    return dataclasses.replace(inp, depth_m=depth, class_id=cls)


def require_image_source(path: Path, given: str) -> None:
    """Refuse predicted depth / classes (``given`` names them, e.g. ``--model-depth``) for a SOURCE that is not an
    image: a scene or mesh has exact depth and classes and would never ask the networks.

    Raises:
        InputError: ``path`` is not an image source (:data:`IMAGE_SUFFIXES`).
    """
    if Path(path).suffix.lower() not in IMAGE_SUFFIXES:
        raise InputError(f"{path}: {given} replace the depth / classes of an image source "
                         f"({', '.join(IMAGE_SUFFIXES)}); a scene or mesh source has exact ones and would not use "
                         "the networks. Drop the option, or give an image (SCENE/rgb/NNNNNN.png or an .npz)")


def load_source(path: Path, *, image_config: object | None = None, depth_fn: DepthFn | None = None,
                seg_fn: SegFn | None = None, unit: str | None = None) -> LayeredMesh:
    """The layered mesh of any SOURCE (see the module docstring); world frame when a pose is known.

    ``depth_fn`` / ``seg_fn`` replace an image source's depth / classes by predictions (:func:`with_predictions`);
    ``unit`` is a mesh file's length unit (``m``, ``cm``, ``mm``, ``in``; see :func:`ply_mesh`, :func:`cad_mesh`).

    Raises:
        InputError: an unsupported SOURCE, ``depth_fn`` / ``seg_fn`` with a scene or mesh
        (:func:`require_image_source`), or ``unit`` with a source that is not a mesh file.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if depth_fn is not None or seg_fn is not None:
        require_image_source(path, " and ".join(n for n, f in (("depth_fn", depth_fn), ("seg_fn", seg_fn)) if f))
    if unit is not None and suffix not in MESH_SUFFIXES:
        raise InputError(f"{path}: a unit applies to a mesh file ({', '.join(MESH_SUFFIXES)}); a scene spec gives "
                         "each object's unit and an image's depth is in metres. Drop the unit")
    if suffix in SCENE_SUFFIXES:
        return scene_mesh(path)
    if suffix == ".ply":
        return ply_mesh(path, unit)
    if suffix in MESH_SUFFIXES:
        return cad_mesh(path, unit)
    if suffix in IMAGE_SUFFIXES:
        inp = with_predictions(read_image_input(path), depth_fn, seg_fn)
        return mesh_from_image(inp, image_config or PRESETS["default"])
    raise InputError(f"unsupported SOURCE {path}: use a scene spec ({', '.join(SCENE_SUFFIXES)}), a mesh or CAD "
                     f"file ({', '.join(MESH_SUFFIXES)}), or an image ({', '.join(IMAGE_SUFFIXES)})")

"""Assemble a scene spec into meshes with world poses, classes, model ids and textures."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from cadalign.cad import load_cad
from cadalign.cad.procedural import DEFAULT_SIZES_M, make_part, seabed
from cadalign.errors import InputError
from cadalign.sim.spec import ObjectSpec, SceneSpec, check_mesh_clearance, resolve_source, split_part
from cadalign.types import Camera, Rigid3

log = logging.getLogger(__name__)

SEABED_INSTANCE = 0


@dataclass(frozen=True)
class SimObject:
    """One object instance of the scene.

    Attributes:
        name: instance name from the spec.
        obj_id: BOP model id (instances of the same mesh share it), 1-based.
        class_id: index into the scene's class list (> 0).
        mesh: the model in its own frame, metres.
        T_world_from_obj: pose of the instance in the world.
        texture: material name.
        spec: the object's spec entry.
    """

    name: str
    obj_id: int
    class_id: int
    mesh: trimesh.Trimesh
    T_world_from_obj: Rigid3
    texture: str
    spec: ObjectSpec


@dataclass(frozen=True)
class SimScene:
    spec: SceneSpec
    objects: tuple[SimObject, ...]
    models: dict[int, trimesh.Trimesh]
    """BOP model id -> mesh in the model frame (metres)."""
    model_symmetry: dict[int, str]
    seabed: trimesh.Trimesh | None
    camera: Camera


def pose_from_spec(position: tuple[float, float, float], rpy_deg: tuple[float, float, float]) -> Rigid3:
    """World pose from position and extrinsic-xyz roll/pitch/yaw in degrees."""
    R = Rotation.from_euler("xyz", rpy_deg, degrees=True).as_matrix()
    return Rigid3(R, position)


def camera_from_spec(spec: SceneSpec, width: int | None = None, height: int | None = None) -> Camera:
    """Pinhole intrinsics from the horizontal FOV; principal point at the image centre."""
    w = width or spec.camera.width
    h = height or spec.camera.height
    f = 0.5 * w / np.tan(np.radians(spec.camera.hfov_deg) / 2)
    K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
    return Camera(K, w, h)


def _load_mesh(o: ObjectSpec, scene_path: Path | None) -> trimesh.Trimesh:
    if o.source.startswith("procedural:"):
        kind = o.source.split(":", 1)[1]
        if kind not in DEFAULT_SIZES_M:
            raise InputError(f"object '{o.name}': unknown procedural part '{kind}'; allowed: {list(DEFAULT_SIZES_M)}")
        mesh = make_part(kind, o.size_m)
    else:
        model = load_cad(resolve_source(o.source, scene_path), unit=o.unit, name=o.name,
                         part=split_part(o.source)[1])
        mesh = trimesh.Trimesh(model.vertices_m, model.faces, process=False)
    if o.scale != 1.0:
        mesh.apply_scale(o.scale)
    return mesh


def build_scene(spec: SceneSpec, scene_path: Path | None = None, *, width: int | None = None,
                height: int | None = None) -> SimScene:
    """Load every object's mesh, assign BOP model ids and class ids, and set up the camera."""
    model_keys: dict[tuple, int] = {}
    models: dict[int, trimesh.Trimesh] = {}
    symmetry: dict[int, str] = {}
    objects = []
    for o in spec.objects:
        key = (o.source, o.size_m, o.scale, o.unit)
        if key not in model_keys:
            model_keys[key] = len(model_keys) + 1
            models[model_keys[key]] = _load_mesh(o, scene_path)
            symmetry[model_keys[key]] = o.symmetry
        obj_id = model_keys[key]
        objects.append(
            SimObject(o.name, obj_id, spec.classes.index(o.class_name), models[obj_id],
                      pose_from_spec(o.position, o.rpy_deg), o.texture, o)
        )
    check_mesh_clearance(spec, [(o.T_world_from_obj.apply(o.mesh.vertices), o.mesh.faces) for o in objects],
                         str(scene_path) if scene_path is not None else "<scene>")
    bed = None
    if spec.seabed is not None:
        bed = seabed(spec.seabed.size_m, spec.seabed.relief_m, spec.seed)
    return SimScene(spec, tuple(objects), models, symmetry, bed, camera_from_spec(spec, width, height))


def triplanar_uv(mesh: trimesh.Trimesh, tile_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unmerge faces and give each corner a box-projected texture coordinate.

    Returns:
        positions (3F, 3), normals (3F, 3), uv (3F, 2), indices (F, 3).
    """
    tri = mesh.vertices[mesh.faces]  # (F, 3, 3)
    fn = mesh.face_normals
    axis = np.argmax(np.abs(fn), axis=1)
    other = np.array([[1, 2], [0, 2], [0, 1]])[axis]  # (F, 2)
    uv = np.take_along_axis(tri, other[:, None, :].repeat(3, 1), axis=2) / tile_m
    positions = tri.reshape(-1, 3)
    normals = np.repeat(fn, 3, axis=0)
    indices = np.arange(len(positions)).reshape(-1, 3)
    return positions, normals, uv.reshape(-1, 2), indices

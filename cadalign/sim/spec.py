"""Scene spec: the validated content of a scene TOML file.

World frame: metres, z up, the seabed at z = 0. Object poses are given as a
position and roll/pitch/yaw in degrees (extrinsic x-y-z, ``R = Rz(yaw) Ry(pitch) Rx(roll)``);
Euler angles appear only here, at I/O.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from cadalign.cad.inside import inside_mesh
from cadalign.cad.procedural import DEFAULT_SIZES_M
from cadalign.config import from_dict, read_mapping
from cadalign.errors import ConfigError, InputError
from cadalign.sim.effects_chain import build_chain
from cadalign.sim.scene_spec import (
    CameraSpec,
    JerlovType,
    LightSpec,
    ObjectSpec,
    SceneSpec,
    SeabedSpec,
    TextureName,
    TrajectoryKind,
    TrajectorySpec,
    WaterSpec,
)
from cadalign.sim.trajectory import pose_at

__all__ = [
    "CameraSpec", "JerlovType", "LightSpec", "ObjectSpec", "SceneSpec", "SeabedSpec", "TextureName", "TrajectoryKind",
    "TrajectorySpec", "WaterSpec", "check_camera_clearance", "check_mesh_clearance", "data_dir", "default_scene_path",
    "load_scene", "resolve_source", "split_part",
]

def load_scene(path: Path) -> SceneSpec:
    """Read and strictly validate a scene TOML/YAML file.

    A file may start from another scene: ``extends = "default.toml"`` (a path relative to the file) loads that
    scene and applies this file's keys over it. Tables merge key by key (``[trajectory]`` can change one
    knob); lists (``[[objects]]``, ``[[lights]]``, effects) replace the base's whole list. The base's mesh
    paths stay relative to the base file.
    """
    path = Path(path)
    spec = _read_scene(path, ())
    try:
        build_chain(spec, source=str(path))  # validates effect names and parameter tables now, not mid-render
    except ConfigError as exc:
        if str(path) in str(exc):
            raise
        raise ConfigError(f"{path}: {exc}") from exc
    check_camera_clearance(spec, source=str(path))
    return spec


def _read_scene(path: Path, seen: tuple[Path, ...]) -> SceneSpec:
    """The scene of ``path`` with its ``extends`` chain applied (``seen``: the files extending it)."""
    data = dict(read_mapping(path))
    parent = data.pop("extends", None)
    if parent is None:
        return from_dict(SceneSpec, data, source=str(path))
    if not isinstance(parent, str) or not parent:
        raise ConfigError(f"{path}: extends must name a scene file, got {parent!r}")
    base_path = (path.parent / parent).resolve()
    if base_path in seen or base_path == path.resolve():
        raise ConfigError(f"{path}: extends {parent!r} makes a loop ({' -> '.join(map(str, (*seen, path)))}); "
                          "a scene cannot extend itself")
    if not base_path.is_file():
        raise ConfigError(f"{path}: extends {parent!r}, but {base_path} is not a file; the path is relative to "
                          f"{path.parent}")
    base = _read_scene(base_path, (*seen, path.resolve()))
    objects = tuple(replace(o, source=_anchored(o.source, base_path)) for o in base.objects)
    return from_dict(SceneSpec, data, source=str(path), base=replace(base, objects=objects))


def _anchored(source: str, scene_path: Path) -> str:
    """A mesh source as the scene at ``scene_path`` meant it, readable from any other folder."""
    if source.startswith(("data:", "procedural:")) or Path(source).is_absolute():
        return source
    return str((scene_path.parent / source).resolve())


def _inside_solid(spec: ObjectSpec, p_world: np.ndarray) -> np.ndarray:
    """(N,) whether world points lie inside a procedural box or cylinder (other parts: never)."""

    kind = spec.source.split(":", 1)[1] if spec.source.startswith("procedural:") else ""
    if kind not in ("box", "cylinder"):
        return np.zeros(len(p_world), bool)
    size = np.asarray(spec.size_m or DEFAULT_SIZES_M[kind], dtype=np.float64) * spec.scale
    R = Rotation.from_euler("xyz", spec.rpy_deg, degrees=True).as_matrix()
    p = (p_world - np.asarray(spec.position)) @ R  # object frame: base centre at the origin, z up
    in_z = (p[:, 2] > 0) & (p[:, 2] < size[2])
    if kind == "box":
        return in_z & np.all(np.abs(p[:, :2]) < size[:2] / 2, axis=1)
    return in_z & (np.sum((p[:, :2] / (size[:2] / 2)) ** 2, axis=1) < 1)


def _camera_centres(spec: SceneSpec, source: str, max_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(frame indices (K,), camera centres (K, 3)) of at most ``max_frames`` evenly spaced frames."""
    traj = spec.trajectory
    ks = np.unique(np.linspace(0, traj.frames - 1, min(traj.frames, max_frames)).round().astype(int))
    try:
        with np.errstate(all="ignore"):  # absurd sizes overflow to a non-finite pose, refused just below
            eyes = np.array([pose_at(traj, k / traj.fps, spec.seed).t for k in ks])
    except ValueError as exc:  # look_at with coincident eye and target, or a non-finite pose
        raise ConfigError(
            f"{source}: [trajectory] gives no valid camera pose ({exc}); move 'center' or the path"
        ) from exc
    return ks, eyes


def check_camera_clearance(spec: SceneSpec, source: str = "<scene>", max_frames: int = 2000) -> None:
    """Refuse trajectories that put the camera under the seabed or inside a solid procedural part.

    Cheap and conservative: camera centres of every frame (at most ``max_frames`` evenly spaced
    ones for very long clips) against the seabed plane (z = 0) and the exact volumes of procedural
    boxes and cylinders; the other parts (CAD meshes, frames, valves) are checked against their meshes by
    :func:`check_mesh_clearance` once they are loaded (:func:`cadalign.sim.scene.build_scene`).

    Raises:
        ConfigError: naming the file, the first offending frame, its position and the fix.
    """
    ks, eyes = _camera_centres(spec, source, max_frames)
    if spec.seabed is not None and np.any(eyes[:, 2] <= 0):
        i = int(np.flatnonzero(eyes[:, 2] <= 0)[0])
        raise ConfigError(f"{source}: the camera of frame {ks[i]} is under the seabed (z = {eyes[i, 2]:.3g} m); "
                          "raise trajectory.height_m above 0 (the seabed is at z = 0)")
    for o in spec.objects:
        inside = _inside_solid(o, eyes)
        if inside.any():
            i = int(np.flatnonzero(inside)[0])
            k = int(ks[i])
            raise ConfigError(
                f"{source}: the camera of frame {k} at {np.round(eyes[i], 3).tolist()} m is inside object "
                f"'{o.name}' ({o.source}); change the trajectory (radius_m, height_m, center) or the object's "
                "position/size_m")


def check_mesh_clearance(spec: SceneSpec, meshes: Sequence[tuple[np.ndarray, np.ndarray]], source: str = "<scene>",
                         max_frames: int = 2000) -> None:
    """Refuse trajectories that put the camera inside a mesh part: CAD files and the procedural parts other than
    boxes and cylinders (which :func:`check_camera_clearance` tests exactly before any mesh is loaded).

    ``meshes[i]`` is ``(vertices (V, 3) in the world, metres; faces (F, 3))`` of ``spec.objects[i]``. The test is
    the generalised winding number (:mod:`cadalign.cad.inside`), robust to small holes of real CAD exports; only
    camera centres inside a part's bounding box are tested, so it costs nothing for cameras outside the parts.

    Raises:
        ConfigError: naming the file, the first offending frame, its position, the object and the fix.
    """

    ks, eyes = _camera_centres(spec, source, max_frames)
    for o, (vertices, faces) in zip(spec.objects, meshes, strict=True):
        if o.source in ("procedural:box", "procedural:cylinder"):
            continue
        inside = inside_mesh(vertices, faces, eyes)
        if inside.any():
            i = int(np.flatnonzero(inside)[0])
            raise ConfigError(
                f"{source}: the camera of frame {int(ks[i])} at {np.round(eyes[i], 3).tolist()} m is inside object "
                f"'{o.name}' ({o.source}); change the trajectory (radius_m, height_m, center) or the object's "
                "position/scale")


def data_dir() -> Path:
    """The shared data folder: $CADALIGN_DATA_DIR, else ``../shared/data`` beside the repository."""
    env = os.environ.get("CADALIGN_DATA_DIR")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "data"


def split_part(source: str) -> tuple[str, str | None]:
    """``"panel.step#valve_1"`` -> ``("panel.step", "valve_1")``: a mesh source and the named part of the file it
    selects (a STEP product, a scene node of a mesh file); ``(source, None)`` without ``#``."""
    file, sep, part = source.partition("#")
    return (file, part) if sep and part else (file, None)


def resolve_source(source: str, scene_path: Path | None) -> Path:
    """Resolve an object's mesh `source` to a file path (procedural sources are not files; a ``#part`` suffix is
    dropped, see :func:`split_part`)."""
    source = split_part(source)[0]
    if source.startswith("data:"):
        p = data_dir() / source[len("data:") :]
        hint = "set CADALIGN_DATA_DIR to the folder holding uuv_subsea_cad/"
    else:
        base = scene_path.parent if scene_path is not None else Path.cwd()
        p = (base / source).resolve()
        hint = "paths are relative to the scene file"
    if not p.is_file():
        raise InputError(f"mesh not found for source '{source}': {p} ({hint})")
    return p


def default_scene_path() -> Path:
    """The embedded default scene shipped with the repository."""
    return Path(__file__).resolve().parents[2] / "datasets" / "scenes" / "default.toml"

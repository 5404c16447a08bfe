"""Scene spec: the validated content of a scene TOML file.

World frame: metres, z up, the seabed at z = 0. Object poses are given as a
position and roll/pitch/yaw in degrees (extrinsic x-y-z, ``R = Rz(yaw) Ry(pitch) Rx(roll)``);
Euler angles appear only here, at I/O.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from cadalign.config import bounded, from_dict, read_mapping
from cadalign.errors import ConfigError, InputError

TrajectoryKind = Literal["orbit", "lawnmower", "approach", "hover"]
TextureName = Literal["painted_steel", "yellow_paint", "rust", "marine_growth", "sediment", "galvanised"]


@dataclass(frozen=True)
class CameraSpec:
    width: int = bounded(640, ge=8)
    """Image width in pixels."""
    height: int = bounded(480, ge=8)
    """Image height in pixels."""
    hfov_deg: float = bounded(70.0, gt=1.0, lt=179.0)
    """Horizontal field of view in degrees (square pixels, principal point at the centre)."""


@dataclass(frozen=True)
class TrajectorySpec:
    kind: TrajectoryKind = "orbit"
    """orbit: circle around `center`; lawnmower: back-and-forth lines over an area;
    approach: straight line towards `center` from `radius_m` to `standoff_m`; hover: station keeping with jitter."""
    center: tuple[float, float, float] = (0.0, 0.0, 2.0)
    """The point the camera looks at (orbit/approach/hover) or the area centre (lawnmower), metres."""
    radius_m: float = bounded(9.0, gt=0.0)
    """Orbit radius / approach start distance / hover distance, metres."""
    height_m: float = 3.0
    """Camera height above the seabed, metres."""
    standoff_m: float = bounded(3.0, gt=0.0)
    """Approach: final distance to `center`, metres."""
    start_deg: float = 0.0
    """Orbit/approach/hover: azimuth of the start position, degrees."""
    climb_m_per_lap: float = 0.0
    """Orbit: height change per full turn, metres (a helix; negative descends). 0 flies one circle over and over."""
    radius_step_m_per_lap: float = 0.0
    """Orbit: radius change per full turn, metres (a spiral; negative closes in). Together with `climb_m_per_lap`
    a second lap sees every side again from another height and distance, as an ROV's second inspection pass does."""
    squareness: float = bounded(2.0, ge=2.0, le=20.0)
    """Orbit: exponent n of the plan shape |x|^n + |y|^n = radius^n. 2 is a circle; larger values give a rounded
    square that keeps `radius_m` from the centre at the middle of each side, so the ROV stays close to every face of
    a box-shaped structure without running into its corners."""
    area_m: tuple[float, float] = (12.0, 12.0)
    """Lawnmower: size of the surveyed rectangle, metres."""
    line_spacing_m: float = bounded(3.0, gt=0.0)
    """Lawnmower: distance between survey lines, metres."""
    pitch_down_deg: float = bounded(35.0, ge=0.0, le=90.0)
    """Lawnmower: camera pitch below the horizon, degrees."""
    speed_mps: float = bounded(0.5, gt=0.0)
    """ROV speed along the path, metres per second (sets frame spacing and motion blur).
    Orbits wrap around; lawnmower and approach paths hold at their end."""
    fps: float = bounded(0.5, gt=0.0)
    """Frames per second of the rendered clip (frame k is at time k / fps)."""
    frames: int = bounded(60, ge=1)
    """Number of frames (overridable with --frames)."""
    jitter_m: float = bounded(0.02, ge=0.0)
    """Smooth positional jitter amplitude (ROV station keeping), metres."""
    shutter_s: float = bounded(0.02, ge=0.0)
    """Exposure time, seconds (motion blur integrates the motion over it)."""


JerlovType = Literal["I", "IA", "IB", "II", "III", "1C", "3C", "5C", "7C", "9C"]


@dataclass(frozen=True)
class WaterSpec:
    jerlov: JerlovType = "II"
    """Jerlov water type (I, IA, IB, II, III, 1C, 3C, 5C, 7C, 9C); ignored when beta_D is given."""
    beta_D: tuple[float, float, float] | None = bounded(None, ge=0.0)
    """Explicit direct-signal attenuation per R,G,B channel, 1/m (>= 0)."""
    beta_B: tuple[float, float, float] | None = bounded(None, ge=0.0)
    """Explicit backscatter coefficient per R,G,B channel, 1/m (>= 0)."""
    B_inf: tuple[float, float, float] | None = bounded(None, ge=0.0, le=1.0)
    """Explicit veiling light per R,G,B channel, linear [0, 1]."""


@dataclass(frozen=True)
class LightSpec:
    offset_m: tuple[float, float, float] = bounded((0.0, -0.3, 0.0), ge=-100.0, le=100.0)
    """Lamp position in the camera frame (x right, y down, z forward), metres (within 100 m of the camera)."""
    direction: tuple[float, float, float] = bounded((0.0, 0.0, 1.0), ge=-1e6, le=1e6)
    """Lamp axis in the camera frame (non-zero; any length, each component within +-1e6)."""
    intensity: float = bounded(40.0, ge=0.0)
    """Radiant intensity on the axis (irradiance at 1 m, before attenuation)."""
    cone_deg: float = bounded(60.0, gt=0.0, le=90.0)
    """Half-angle of the lamp cone, degrees."""


@dataclass(frozen=True)
class SeabedSpec:
    size_m: float = bounded(40.0, gt=0.0)
    """Side of the square seabed patch, metres."""
    relief_m: float = bounded(0.15, ge=0.0)
    """Amplitude of the seabed's height noise, metres."""
    texture: TextureName = "sediment"


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    """Instance name (unique in the scene)."""
    source: str
    """'procedural:KIND' (frame, valve_a..valve_d, hot_stab, box, cylinder), 'data:REL/PATH' (under
    the shared data folder, $CADALIGN_DATA_DIR), or a mesh/STEP/IGES path relative to the scene file.
    ``FILE#PART`` keeps one named part of the file, e.g. ``"panel.step#valve_1"`` (a STEP assembly's product);
    the part keeps its place in the file's frame."""
    class_name: str = "structure"
    """One of the scene's `classes`."""
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Object origin in the world, metres."""
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Roll, pitch, yaw in degrees (extrinsic xyz)."""
    unit: Literal["m", "cm", "mm", "in"] | None = None
    """Unit of the source mesh file; None = detect from its extents (with a warning)."""
    scale: float = bounded(1.0, gt=0.0)
    """Extra uniform scale applied after unit conversion (for procedural size variants)."""
    texture: TextureName = "painted_steel"
    size_m: tuple[float, float, float] | None = None
    """Procedural parts: bounding size (x, y, z) in metres; None = the part's default."""
    symmetry: Literal["none", "continuous_z", "continuous_x", "continuous_y", "discrete_x2", "discrete_y2",
                      "discrete_z2", "discrete_x4", "discrete_y4", "discrete_z4"] = "none"
    """Symmetry of the part in its own frame (BOP symmetries are derived from it)."""


@dataclass(frozen=True)
class SceneSpec:
    name: str
    objects: tuple[ObjectSpec, ...]
    classes: tuple[str, ...] = ("background", "structure", "valve", "hot_stab")
    """Class names; index 0 must be 'background' (seabed and open water)."""
    seed: int = 0
    effects: tuple[str, ...] = ()
    """The water effects to simulate, by name; any effect not listed is never run."""
    camera: CameraSpec = CameraSpec()
    trajectory: TrajectorySpec = TrajectorySpec()
    water: WaterSpec = WaterSpec()
    lights: tuple[LightSpec, ...] = (LightSpec(offset_m=(-0.4, -0.2, 0.0)), LightSpec(offset_m=(0.4, -0.2, 0.0)))
    seabed: SeabedSpec | None = SeabedSpec()
    ambient: float = bounded(0.35, gt=0.0, le=2.0)
    """Ambient (down-welling) light level of the clean render: its colours are albedo × ambient."""
    effect_params: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Per-effect parameter tables, e.g. ``[effect_params.marine_snow] density_per_m3 = 20``.
    Water and lamps come from [water] and [[lights]]."""

    def __post_init__(self) -> None:
        if not self.classes or self.classes[0] != "background":
            raise ValueError(f"classes must start with 'background', got {list(self.classes)}")
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            raise ValueError(f"object names must be unique, got duplicates in {names}")
        for o in self.objects:
            if o.class_name not in self.classes[1:]:
                raise ValueError(f"object '{o.name}' has class '{o.class_name}'; allowed: {list(self.classes[1:])}")
        if not self.objects:
            raise ValueError("a scene needs at least one object")
        from cadalign.cad.procedural import DEFAULT_SIZES_M

        for o in self.objects:
            kind = o.source.split(":", 1)[1] if o.source.startswith("procedural:") else None
            if kind is not None and kind not in DEFAULT_SIZES_M:
                raise ValueError(f"object '{o.name}': unknown procedural part '{kind}'; allowed: "
                                 f"{', '.join('procedural:' + k for k in DEFAULT_SIZES_M)}")


def load_scene(path: Path) -> SceneSpec:
    """Read and strictly validate a scene TOML/YAML file.

    A file may start from another scene: ``extends = "default.toml"`` (a path relative to the file) loads that
    scene and applies this file's keys over it. Tables merge key by key (``[trajectory]`` can change one
    knob); lists (``[[objects]]``, ``[[lights]]``, effects) replace the base's whole list. The base's mesh
    paths stay relative to the base file.
    """
    path = Path(path)
    spec = _read_scene(path, ())
    from cadalign.sim.effects_chain import build_chain

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
    from scipy.spatial.transform import Rotation

    from cadalign.cad.procedural import DEFAULT_SIZES_M

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
    from cadalign.sim.trajectory import pose_at

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
    from cadalign.cad.inside import inside_mesh

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

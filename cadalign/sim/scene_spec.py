"""The scene spec's dataclasses: the validated content of a scene TOML file (read by :mod:`cadalign.sim.spec`).

World frame: metres, z up, the seabed at z = 0. Object poses are given as a
position and roll/pitch/yaw in degrees (extrinsic x-y-z, ``R = Rz(yaw) Ry(pitch) Rx(roll)``);
Euler angles appear only here, at I/O. Kept apart from the file reading so the trajectory and the effect chain,
which the reader runs to validate a scene, import the types without importing the reader.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from cadalign.cad.procedural import DEFAULT_SIZES_M
from cadalign.config import bounded

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
    movable: bool = False
    """The part may move relative to the structure (a hot stab tool in an ROV's grip): the tracker follows it
    on its own instead of placing it by the structure's pose. The simulator draws it where ``position`` says."""


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

        for o in self.objects:
            kind = o.source.split(":", 1)[1] if o.source.startswith("procedural:") else None
            if kind is not None and kind not in DEFAULT_SIZES_M:
                raise ValueError(f"object '{o.name}': unknown procedural part '{kind}'; allowed: "
                                 f"{', '.join('procedural:' + k for k in DEFAULT_SIZES_M)}")

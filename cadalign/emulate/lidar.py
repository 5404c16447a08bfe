"""Spinning LiDAR and uniform-sphere scans by ray casting a :class:`~cadalign.emulate.mesh.LayeredMesh`.

Sensor frame (ROS REP 103): x forward, y left, z up; azimuth is measured from x towards y, elevation from
the x-y plane towards z. A spinning LiDAR fires ``channels`` beams at fixed elevations (evenly spread over
``vfov_deg`` or given explicitly) at every ``horizontal_res_deg`` of azimuth; returns beyond
``max_range_m`` or closer than ``min_range_m`` are lost, and with ``dropout`` a random share of the rest.
Range noise is Gaussian along the beam. Every random choice comes from ``seed``.

Each return carries xyz (world), range, RGB, class, part id and pane id from the mesh's layers.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from cadalign.config import bounded
from cadalign.emulate.mesh import LayeredMesh
from cadalign.emulate.raycast_engines import BVHEngine, RayHits, TorchEngine, make_engine
from cadalign.errors import ConfigError
from cadalign.io import atomic_path
from cadalign.types import Rigid3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LidarConfig:
    pattern: Literal["spinning", "sphere"] = "spinning"
    """spinning: rings of fixed elevation swept in azimuth; sphere: directions uniform on the unit sphere."""
    channels: int = bounded(32, ge=1)
    """Spinning: number of beams (rings)."""
    vfov_deg: tuple[float, float] = (-30.67, 10.67)
    """Spinning: lowest and highest beam elevation, degrees (beams evenly spaced between them)."""
    vertical_angles_deg: tuple[float, ...] = ()
    """Spinning: explicit beam elevations in degrees; overrides ``channels`` and ``vfov_deg`` when given."""
    horizontal_res_deg: float = bounded(0.2, gt=0.0, le=360.0)
    """Spinning: azimuth step between firings, degrees."""
    n_rays: int = bounded(100_000, ge=1)
    """Sphere: number of directions."""
    min_range_m: float = bounded(0.1, ge=0.0)
    """Returns closer than this are lost, metres."""
    max_range_m: float = bounded(100.0, gt=0.0)
    """Returns farther than this are lost, metres."""
    range_noise_m: float = bounded(0.01, ge=0.0)
    """Standard deviation of Gaussian range noise, metres."""
    dropout: float = bounded(0.0, ge=0.0, lt=1.0)
    """Probability that a valid return is lost."""
    seed: int = 0
    """Seed of the noise, dropout and sphere directions."""
    engine: Literal["bvh", "torch"] = "bvh"
    """Ray caster: Open3D BVH (fast, CPU) or exact Möller–Trumbore in torch (GPU-capable)."""
    device: str = "cpu"
    """Torch engine device."""

    def __post_init__(self) -> None:
        if self.vfov_deg[0] > self.vfov_deg[1] or not -90 <= self.vfov_deg[0] <= self.vfov_deg[1] <= 90:
            raise ConfigError(f"vfov_deg must be (low, high) within [-90, 90], got {self.vfov_deg}")
        if any(not -90 <= a <= 90 for a in self.vertical_angles_deg):
            raise ConfigError(f"vertical_angles_deg must lie in [-90, 90], got {self.vertical_angles_deg}")
        if self.min_range_m >= self.max_range_m:
            raise ConfigError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")


PRESETS: dict[str, LidarConfig] = {
    "vlp16": LidarConfig(channels=16, vfov_deg=(-15.0, 15.0), horizontal_res_deg=0.2, max_range_m=100.0,
                         range_noise_m=0.03),
    "hdl32": LidarConfig(),
    "os1_128": LidarConfig(channels=128, vfov_deg=(-22.5, 22.5), horizontal_res_deg=360 / 2048, max_range_m=120.0,
                           range_noise_m=0.015),
    "subsea_laser": LidarConfig(channels=64, vfov_deg=(-45.0, 15.0), horizontal_res_deg=0.1, max_range_m=20.0,
                                range_noise_m=0.005, dropout=0.02),
    "sphere_1m": LidarConfig(pattern="sphere", n_rays=1_000_000, max_range_m=1000.0, range_noise_m=0.0),
}
"""Sensor presets: Velodyne VLP-16 / HDL-32E, Ouster OS1-128, a short-range subsea laser scanner, and a
million-ray uniform sphere (the throughput benchmark)."""


@dataclass(frozen=True)
class LidarScan:
    """The returns of one scan (only rays that returned).

    Attributes:
        xyz_world: (N, 3) float64 points, metres.
        range_m: (N,) measured range (with noise), metres.
        rgb: (N, 3) uint8 colour of the surface hit.
        class_id: (N,) int32 class of the surface hit.
        part_id: (N,) int32 part / instance id of the surface hit.
        pane_id: (N,) int32 pane id of the surface hit (0 = not a pane).
        ring: (N,) int32 beam index (spinning) or -1 (sphere).
        azimuth_rad: (N,) azimuth of the beam in the sensor frame.
        elevation_rad: (N,) elevation of the beam in the sensor frame.
        n_rays: number of rays cast.
        origin_world: (3,) the sensor position (ray origin), metres.
    """

    xyz_world: np.ndarray
    range_m: np.ndarray
    rgb: np.ndarray
    class_id: np.ndarray
    part_id: np.ndarray
    pane_id: np.ndarray
    ring: np.ndarray
    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    n_rays: int
    origin_world: np.ndarray


def beam_elevations_deg(cfg: LidarConfig) -> np.ndarray:
    """(C,) beam elevations in degrees, lowest first."""
    if cfg.vertical_angles_deg:
        return np.sort(np.asarray(cfg.vertical_angles_deg, dtype=np.float64))
    if cfg.channels == 1:
        return np.array([0.5 * (cfg.vfov_deg[0] + cfg.vfov_deg[1])])
    return np.linspace(cfg.vfov_deg[0], cfg.vfov_deg[1], cfg.channels)


def uniform_sphere(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) unit vectors uniform on the sphere (normalised Gaussians)."""
    d = rng.standard_normal((int(n), 3))
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    d[norm[:, 0] == 0] = (1.0, 0.0, 0.0)  # probability zero, but never divide by 0
    return d / np.maximum(norm, 1e-300)


def scan_directions(cfg: LidarConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sensor-frame unit directions ``(N, 3)``, ring ``(N,)``, azimuth and elevation ``(N,)`` in firing order.

    Spinning: column by column (all beams at one azimuth, then the next azimuth), as a real sensor fires.
    """
    if cfg.pattern == "sphere":
        d = uniform_sphere(cfg.n_rays, np.random.default_rng([cfg.seed, 1]))
        az = np.arctan2(d[:, 1], d[:, 0])
        el = np.arcsin(np.clip(d[:, 2], -1, 1))
        return d, np.full(len(d), -1, np.int32), az, el
    el1 = np.radians(beam_elevations_deg(cfg))
    n_az = max(1, int(round(360.0 / cfg.horizontal_res_deg)))
    az1 = np.arange(n_az) * (2 * np.pi / n_az)
    az, el = np.meshgrid(az1, el1, indexing="ij")  # (n_az, C): firing order
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1).reshape(-1, 3)
    ring = np.tile(np.arange(len(el1), dtype=np.int32), n_az)
    return d, ring, az.ravel(), el.ravel()


def cast_from(engine: BVHEngine | TorchEngine, T_world_from_sensor: Rigid3, dirs_sensor: np.ndarray) -> RayHits:
    """Cast sensor-frame unit directions ``(N, 3)`` from the sensor's world pose."""
    d = (dirs_sensor @ T_world_from_sensor.R.T).astype(np.float64, copy=False)
    return engine.cast_unit(T_world_from_sensor.t, d)


def scan(mesh: LayeredMesh, T_world_from_sensor: Rigid3, cfg: LidarConfig,
         engine: BVHEngine | TorchEngine | None = None,
         pattern: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None) -> LidarScan:
    """One LiDAR scan of ``mesh`` from ``T_world_from_sensor``.

    Pass ``engine`` (built over ``mesh``) and ``pattern`` (:func:`scan_directions` of ``cfg``) to reuse them
    over many scans: the beam pattern of a sensor is fixed, only its pose changes.
    """
    engine = engine or make_engine(cfg.engine, mesh.vertices_m, mesh.faces, device=cfg.device)
    d, ring, az, el = pattern if pattern is not None else scan_directions(cfg)
    d_world = d @ T_world_from_sensor.R.T
    hits = engine.cast_unit(T_world_from_sensor.t, d_world)
    rng = np.random.default_rng([cfg.seed, 2])
    r = hits.range_m
    keep = hits.hit & (r >= cfg.min_range_m) & (r <= cfg.max_range_m)
    if cfg.dropout > 0:
        keep &= rng.random(len(r)) >= cfg.dropout
    idx = np.flatnonzero(keep)
    r_meas = r[idx]
    if cfg.range_noise_m > 0:
        r_meas = np.maximum(r_meas + rng.standard_normal(len(idx)) * cfg.range_noise_m, 0.0)
    f = hits.face[idx]
    return LidarScan(
        T_world_from_sensor.t + d_world[idx] * r_meas[:, None], r_meas, mesh.hit_rgb(f, hits.bary[idx]),
        mesh.class_id[f], mesh.part_id[f], mesh.pane_id[f], ring[idx], az[idx], el[idx], len(d),
        np.array(T_world_from_sensor.t),
    )


def write_npz(scan_: LidarScan, path: Path) -> Path:
    """All fields of the scan in one compressed ``.npz`` (atomic)."""
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **{k: getattr(scan_, k) for k in LidarScan.__dataclass_fields__})
    return Path(path)


def write_ply(scan_: LidarScan, path: Path) -> Path:
    """Binary PLY point cloud: x y z (double), red green blue, range, class, part, pane, ring (atomic)."""
    dt = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
          ("range", "<f4"), ("class", "<i4"), ("part", "<i4"), ("pane", "<i4"), ("ring", "<i4")]
    a = np.zeros(len(scan_.range_m), dtype=dt)
    a["x"], a["y"], a["z"] = scan_.xyz_world.T
    a["red"], a["green"], a["blue"] = scan_.rgb.T
    a["range"], a["class"], a["part"], a["pane"], a["ring"] = (
        scan_.range_m, scan_.class_id, scan_.part_id, scan_.pane_id, scan_.ring)
    types = {"<f8": "double", "u1": "uchar", "<f4": "float", "<i4": "int"}
    header = ("ply\nformat binary_little_endian 1.0\ncomment cadalign emulated lidar (metres, world frame)\n"
              f"element vertex {len(a)}\n" + "".join(f"property {types[t]} {n}\n" for n, t in dt) + "end_header\n")
    with atomic_path(Path(path)) as tmp:
        tmp.write_bytes(header.encode("ascii") + a.tobytes())
    return Path(path)

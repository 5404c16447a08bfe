"""Multibeam imaging (forward-looking) sonar: a range x bearing intensity image from ray returns.

Sensor frame as the LiDAR's: x forward, y left, z up. Beam ``b`` looks at bearing ``theta_b`` (from x
towards y) across ``hfov_deg``; each beam integrates ``elevation_samples`` rays spread over the vertical
aperture ``vfov_deg`` - a sonar cannot tell elevation apart, so every return of the fan lands in the
(range bin, beam) cell of its range and bearing. One return contributes

    reflectivity[class] * |cos(incidence)| ** incidence_exponent * 10 ** (-2 * alpha * r / 10) * r ** -spreading

(Lambertian-like backscatter, two-way absorption ``alpha`` in dB/m, geometric spreading relative to 1 m),
divided by the rays per beam. Speckle is multiplicative Gamma noise with ``speckle_looks`` looks (1 = fully
developed speckle, exponential intensity) and the receiver adds an exponential noise floor. Every random
choice comes from ``seed``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from cadalign.config import bounded
from cadalign.emulate.lidar import cast_from
from cadalign.emulate.mesh import LayeredMesh
from cadalign.emulate.raycast_engines import BVHEngine, TorchEngine, make_engine
from cadalign.errors import ConfigError
from cadalign.types import Rigid3


@dataclass(frozen=True)
class SonarConfig:
    n_beams: int = bounded(256, ge=1)
    """Number of beams across the horizontal fan."""
    hfov_deg: float = bounded(130.0, gt=0.0, lt=360.0)
    """Horizontal field of view (bearing span), degrees."""
    vfov_deg: float = bounded(20.0, ge=0.0, lt=180.0)
    """Vertical aperture of every beam, degrees."""
    elevation_samples: int = bounded(512, ge=1)
    """Rays per beam across the vertical aperture (stratified)."""
    jitter: bool = True
    """Jitter each ray inside its elevation stratum and across the beam's width (seeded): the beam integrates
    its whole footprint instead of sampling fixed lines."""
    min_range_m: float = bounded(0.5, ge=0.0)
    """Start of the range window, metres."""
    max_range_m: float = bounded(30.0, gt=0.0)
    """End of the range window, metres."""
    range_bins: int = bounded(512, ge=1)
    """Range samples between min_range_m and max_range_m."""
    class_reflectivity: tuple[float, ...] = (0.4, 1.0, 1.0, 1.0)
    """Backscatter strength per class id (index = class; classes beyond the list get 1.0)."""
    incidence_exponent: float = bounded(2.0, ge=0.0)
    """Exponent k of the |cos(incidence)|^k backscatter law (0 = incidence-independent)."""
    attenuation_db_per_m: float = bounded(0.1, ge=0.0)
    """Absorption in water, dB per metre, applied on the way out and back."""
    spreading_exponent: float = bounded(0.0, ge=0.0)
    """Geometric spreading r^-k relative to 1 m (0 = fully compensated by the sonar's time-varied gain)."""
    speckle_looks: float = bounded(1.0, ge=0.0)
    """Gamma speckle looks (1 = fully developed speckle; 0 = no speckle)."""
    noise_floor: float = bounded(1e-5, ge=0.0)
    """Mean of the additive exponential receiver noise, in intensity units."""
    dynamic_range_db: float = bounded(50.0, gt=0.0)
    """Span shown by the 8-bit image, below the strongest cell, dB."""
    seed: int = 0
    """Seed of speckle and noise."""
    engine: Literal["bvh", "torch"] = "bvh"
    """Ray caster."""
    device: str = "cpu"
    """Torch engine device."""

    def __post_init__(self) -> None:
        if self.min_range_m >= self.max_range_m:
            raise ConfigError(f"min_range_m ({self.min_range_m}) must be below max_range_m ({self.max_range_m})")


PRESETS: dict[str, SonarConfig] = {
    "oculus_m750d": SonarConfig(n_beams=512, hfov_deg=130.0, vfov_deg=20.0, max_range_m=40.0, range_bins=640),
    "aris_3000": SonarConfig(n_beams=128, hfov_deg=30.0, vfov_deg=14.0, min_range_m=0.7, max_range_m=15.0,
                             range_bins=1024, attenuation_db_per_m=0.3),
    "default": SonarConfig(),
    "fast": SonarConfig(n_beams=128, elevation_samples=96, range_bins=256),
}
"""Presets: a Blueprint Oculus M750d-like wide fan, a Sound Metrics ARIS 3000-like narrow high-resolution
fan, the defaults, and a coarse fast one."""


@dataclass(frozen=True)
class SonarImage:
    """One sonar ping.

    Attributes:
        intensity: (range_bins, n_beams) float32 linear intensity (speckle and noise included).
        clean: (range_bins, n_beams) float32 intensity before speckle and noise.
        class_id: (range_bins, n_beams) int32 class of the strongest return per cell; -1 where none.
        ranges_m: (range_bins,) centre range of each bin.
        bearings_rad: (n_beams,) bearing of each beam (positive to the left, +y).
    """

    intensity: np.ndarray
    clean: np.ndarray
    class_id: np.ndarray
    ranges_m: np.ndarray
    bearings_rad: np.ndarray


def beam_directions(cfg: SonarConfig, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sensor-frame unit directions ``(n_beams * elevation_samples, 3)`` and the beam index of each.

    Elevations are stratified over the vertical aperture; with ``cfg.jitter`` (and ``rng``) each ray is moved
    uniformly inside its stratum and across the beam width ``hfov / n_beams``.
    """
    half = np.radians(cfg.hfov_deg) / 2
    bearing = np.linspace(-half, half, cfg.n_beams) if cfg.n_beams > 1 else np.zeros(1)
    e = np.radians(cfg.vfov_deg) / 2
    shape = (cfg.n_beams, cfg.elevation_samples)
    u_el = np.full(shape, 0.5)
    u_az = np.zeros(shape)
    if cfg.jitter and rng is not None:
        u_el = rng.random(shape)
        u_az = (rng.random(shape) - 0.5) * (2 * half / cfg.n_beams)
    el = (np.arange(cfg.elevation_samples)[None] + u_el) / cfg.elevation_samples * 2 * e - e
    b = bearing[:, None] + u_az
    d = np.stack([np.cos(el) * np.cos(b), np.cos(el) * np.sin(b), np.sin(el)], -1).reshape(-1, 3)
    return d, np.repeat(np.arange(cfg.n_beams), cfg.elevation_samples)


def return_strength(cfg: SonarConfig, range_m: np.ndarray, cos_inc: np.ndarray, class_id: np.ndarray) -> np.ndarray:
    """Backscattered intensity of returns (see the module docstring), before the per-beam average."""
    refl = np.asarray(cfg.class_reflectivity, dtype=np.float64)
    cls = np.asarray(class_id, dtype=np.int64)
    r_cls = np.where((cls >= 0) & (cls < len(refl)), refl[np.clip(cls, 0, max(len(refl) - 1, 0))], 1.0)
    atten = 10.0 ** (-2.0 * cfg.attenuation_db_per_m * range_m / 10.0)
    spread = np.maximum(range_m, 1.0) ** -cfg.spreading_exponent
    return r_cls * np.abs(cos_inc) ** cfg.incidence_exponent * atten * spread


def ping(mesh: LayeredMesh, T_world_from_sonar: Rigid3, cfg: SonarConfig,
         engine: BVHEngine | TorchEngine | None = None) -> SonarImage:
    """One ping of ``mesh`` from ``T_world_from_sonar``."""
    engine = engine or make_engine(cfg.engine, mesh.vertices_m, mesh.faces, device=cfg.device)
    rng = np.random.default_rng([cfg.seed, 3])
    d, beam = beam_directions(cfg, rng)
    hits = cast_from(engine, T_world_from_sonar, d)
    width = (cfg.max_range_m - cfg.min_range_m) / cfg.range_bins
    ok = hits.hit & (hits.range_m >= cfg.min_range_m) & (hits.range_m < cfg.max_range_m)
    f, r = hits.face[ok], hits.range_m[ok]
    d_world = d[ok] @ T_world_from_sonar.R.T
    cos_inc = np.einsum("nk,nk->n", mesh.face_normals()[f], d_world)
    val = return_strength(cfg, r, cos_inc, mesh.class_id[f]) / cfg.elevation_samples
    rbin = np.minimum(((r - cfg.min_range_m) / width).astype(np.int64), cfg.range_bins - 1)
    cell = rbin * cfg.n_beams + beam[ok]
    n_cells = cfg.range_bins * cfg.n_beams
    clean = np.bincount(cell, weights=val, minlength=n_cells)
    cls = np.full(n_cells, -1, np.int32)
    order = np.lexsort((val, cell))  # by cell, strongest last
    last = np.flatnonzero(np.r_[cell[order][1:] != cell[order][:-1], True])
    cls[cell[order][last]] = mesh.class_id[f][order][last]
    noisy = clean * (rng.gamma(cfg.speckle_looks, 1.0 / cfg.speckle_looks, n_cells) if cfg.speckle_looks > 0 else 1)
    if cfg.noise_floor > 0:
        noisy = noisy + rng.exponential(cfg.noise_floor, n_cells)
    shape = (cfg.range_bins, cfg.n_beams)
    ranges = cfg.min_range_m + (np.arange(cfg.range_bins) + 0.5) * width
    bearings = np.linspace(-1, 1, cfg.n_beams) * np.radians(cfg.hfov_deg) / 2 if cfg.n_beams > 1 else np.zeros(1)
    return SonarImage(noisy.reshape(shape).astype(np.float32), clean.reshape(shape).astype(np.float32),
                      cls.reshape(shape), ranges, bearings)


def to_uint8(intensity: np.ndarray, dynamic_range_db: float) -> np.ndarray:
    """Log-compressed 8-bit image: the strongest cell is 255, ``dynamic_range_db`` below it is 0."""
    peak = float(np.max(intensity)) if intensity.size else 0.0
    if peak <= 0:
        return np.zeros(intensity.shape, np.uint8)
    db = 10.0 * np.log10(np.maximum(intensity, peak * 1e-12) / peak)
    return np.clip(np.rint((db + dynamic_range_db) / dynamic_range_db * 255), 0, 255).astype(np.uint8)


def fan_image(polar: np.ndarray, img: SonarImage, width_px: int = 800) -> np.ndarray:
    """The polar image (range_bins, n_beams[, C]) drawn as the usual fan (range up, bearing left-right).

    Pixels outside the fan are 0. Nearest-neighbour lookup; the sonar sits at the bottom centre.
    """
    r_max = float(img.ranges_m[-1] + 0.5 * (img.ranges_m[1] - img.ranges_m[0] if len(img.ranges_m) > 1 else 0))
    half = float(np.max(np.abs(img.bearings_rad))) if len(img.bearings_rad) > 1 else np.radians(1.0)
    half_w = r_max * np.sin(min(half, np.pi / 2))
    height_px = max(1, int(round(width_px * r_max / max(2 * half_w, 1e-9))))
    x = (np.arange(width_px) + 0.5) / width_px * 2 * half_w - half_w  # to the right = negative bearing
    y = r_max - (np.arange(height_px) + 0.5) / height_px * r_max
    xx, yy = np.meshgrid(x, y)
    r, b = np.hypot(xx, yy), np.arctan2(-xx, yy)
    width = img.ranges_m[1] - img.ranges_m[0] if len(img.ranges_m) > 1 else r_max
    ri = np.floor((r - (img.ranges_m[0] - width / 2)) / width).astype(np.int64)
    step = (img.bearings_rad[1] - img.bearings_rad[0]) if len(img.bearings_rad) > 1 else 1.0
    bi = np.rint((b - img.bearings_rad[0]) / step).astype(np.int64)
    inside = (ri >= 0) & (ri < len(img.ranges_m)) & (bi >= 0) & (bi < len(img.bearings_rad)) & (np.abs(b) <= half)
    out = np.zeros((height_px, width_px) + polar.shape[2:], dtype=polar.dtype)
    out[inside] = polar[ri[inside], bi[inside]]
    return out

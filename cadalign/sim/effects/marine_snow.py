"""Marine snow: lit particles drifting in the water between the camera and the scene.

Particles are sampled uniformly in volume inside the camera frustum between
``min_range_m`` and ``max_range_m`` (bounds on the z-depth), with lognormal
diameters. Each one is drawn as a soft disc whose radiance is its albedo times
the ambient level plus the lamps' irradiance (so particles near the lamps
glare), attenuated by ``exp(-beta_D * range)`` on the way to the camera. A disc
pixel is drawn only where the particle is closer than the surface seen there.
Particles are sampled per frame (no temporal coherence between frames).

Marine snow aggregates are porous and translucent, mostly water, so the light
from behind a particle passes it nearly undimmed: the disc *adds* its scattered
radiance (weighted by its coverage of the pixel) and never darkens the scene.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cadalign.errors import ConfigError
from cadalign.sim.effects.attenuation import transmission
from cadalign.sim.effects.buffers import FrameBuffers, clean_range
from cadalign.sim.effects.lights import Lamp, lamp_irradiance_at
from cadalign.sim.effects.water import WaterParams, water_from_jerlov

_STAMP_HALF_SIZES = (1, 2, 4, 8, 16)


@dataclass(frozen=True)
class MarineSnowParams:
    density_per_m3: float = 20.0
    """Mean number of visible particles per cubic metre of water."""
    min_range_m: float = 0.15
    """Nearest particle depth (closer ones are out of focus or inside the housing), metres."""
    max_range_m: float = 6.0
    """Farthest particle depth (farther ones are lost in the veiling light), metres."""
    diameter_mm: float = 1.0
    """Median particle diameter, millimetres (lognormal)."""
    diameter_log_sigma: float = 0.6
    """Standard deviation of ln(diameter)."""
    max_radius_px: float = 14.0
    """Apparent radius cap, pixels (bounds the cost of very close particles)."""
    edge_px: float = 1.5
    """Width of the soft disc edge, pixels."""
    opacity: float = 0.85
    """Peak coverage weight of a particle covering whole pixels: the fraction of its radiance added there."""
    albedo: float = 0.8
    """Particle reflectance."""
    ambient: float = 0.35
    """Ambient light level of the clean render (lights particles outside the lamp cones)."""
    lamps: tuple[Lamp, ...] = (Lamp(offset_m=(-0.4, -0.2, 0.0)), Lamp(offset_m=(0.4, -0.2, 0.0)))
    """The ROV's lamps."""
    water: WaterParams = field(default_factory=lambda: water_from_jerlov("II"))
    """Water (``beta_D`` dims the lamp-to-particle and particle-to-camera paths)."""

    def __post_init__(self) -> None:
        checks = {"density_per_m3": self.density_per_m3 >= 0, "min_range_m": self.min_range_m > 0,
                  "max_range_m": self.max_range_m >= self.min_range_m, "diameter_mm": self.diameter_mm > 0,
                  "diameter_log_sigma": self.diameter_log_sigma >= 0,
                  # A disc reaches radius + edge / 2 + 1 px from its pixel: it must fit the largest stamp.
                  "max_radius_px": 0 < self.max_radius_px <= _STAMP_HALF_SIZES[-1] - 1.0 - self.edge_px / 2,
                  "edge_px": self.edge_px > 0, "opacity": 0 <= self.opacity <= 1, "albedo": self.albedo >= 0,
                  "ambient": self.ambient >= 0}
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise ConfigError(f"MarineSnowParams: invalid {', '.join(f'{n}={getattr(self, n)!r}' for n in bad)}")


@dataclass(frozen=True)
class Particles:
    """Sampled particles (N of them).

    Attributes:
        uv: (N, 2) float32 image position, pixels (pixel-centre convention of :mod:`cadalign.types`).
        range_m: (N,) float32 distance from the camera, metres.
        radius_px: (N,) float32 apparent radius, pixels (may be < 1).
        radiance: (N, 3) float32 radiance reaching the camera.
    """

    uv: np.ndarray
    range_m: np.ndarray
    radius_px: np.ndarray
    radiance: np.ndarray


def sample_particles(buffers: FrameBuffers, params: MarineSnowParams, rng: np.random.Generator) -> Particles:
    """Draw the particles of one frame in the camera frustum.

    Args:
        buffers: the frame (camera only).
        params: density, sizes, lamps and water.
        rng: the random generator (the only source of randomness).

    Returns:
        The particles, in no particular order.
    """
    cam = buffers.camera
    z0, z1 = params.min_range_m, params.max_range_m
    volume = (cam.width / cam.fx) * (cam.height / cam.fy) * (z1**3 - z0**3) / 3.0
    n = int(rng.poisson(params.density_per_m3 * volume))
    uv = rng.uniform((0.0, 0.0), (cam.width, cam.height), size=(n, 2)).astype(np.float32)
    z = np.cbrt(z0**3 + rng.uniform(size=n) * (z1**3 - z0**3)).astype(np.float32)  # density ∝ z^2
    diam_m = 1e-3 * params.diameter_mm * np.exp(params.diameter_log_sigma * rng.standard_normal(n))
    xy = (uv - np.array([cam.cx, cam.cy], dtype=np.float32)) / np.array([cam.fx, cam.fy], dtype=np.float32)
    points = np.concatenate([xy, np.ones((n, 1), np.float32)], axis=1) * z[:, None]
    range_m = np.linalg.norm(points, axis=1).astype(np.float32)
    E = lamp_irradiance_at(points, params.lamps, params.water.beta_D)
    radiance = np.float32(params.albedo) * (np.float32(params.ambient) + E * np.float32(1.0 / np.pi))
    radiance *= transmission(range_m, params.water.beta_D)
    radius = np.minimum(0.5 * diam_m * cam.fx / z, params.max_radius_px).astype(np.float32)
    return Particles(uv, range_m, radius, radiance.astype(np.float32))


def _splat(p: Particles, surface_range: np.ndarray, params: MarineSnowParams) -> tuple[np.ndarray, np.ndarray]:
    """Accumulate disc coverage and radiance per pixel: (H*W,) alpha and (H*W, 3) alpha-weighted radiance."""
    H, W = surface_range.shape
    r_eff = np.maximum(p.radius_px, np.float32(0.5))
    # Sub-pixel particles keep their area: a half-pixel disc drawn with opacity scaled by (r / 0.5)^2.
    peak = np.float32(params.opacity) * np.minimum(np.float32(1.0), (p.radius_px / np.float32(0.5)) ** 2)
    reach = r_eff + np.float32(params.edge_px / 2 + 1.0)
    cls = np.searchsorted(np.asarray(_STAMP_HALF_SIZES, dtype=np.float32), reach)
    alpha = np.zeros(H * W, dtype=np.float64)
    color = np.zeros((H * W, 3), dtype=np.float64)
    base = np.floor(p.uv).astype(np.int64)
    for k, h in enumerate(_STAMP_HALF_SIZES):
        sel = np.flatnonzero(cls == k)
        if sel.size == 0:
            continue
        off = np.arange(-h, h + 1)
        ox, oy = (a.ravel() for a in np.meshgrid(off, off))
        px = base[sel, 0:1] + ox
        py = base[sel, 1:2] + oy
        dist = np.hypot(px + 0.5 - p.uv[sel, 0:1], py + 0.5 - p.uv[sel, 1:2])
        a = np.clip((r_eff[sel, None] + params.edge_px / 2 - dist) / params.edge_px, 0.0, 1.0) * peak[sel, None]
        which = np.broadcast_to(sel[:, None], a.shape)
        keep = (px >= 0) & (px < W) & (py >= 0) & (py < H) & (a > 0)
        flat, a, which = (py * W + px)[keep], a[keep], which[keep]
        front = p.range_m[which] < surface_range.ravel()[flat]  # occluded by the surface otherwise
        flat, a, which = flat[front], a[front], which[front]
        alpha += np.bincount(flat, a, minlength=H * W)
        for c in range(3):
            color[:, c] += np.bincount(flat, a * p.radiance[which, c], minlength=H * W)
    return alpha, color


def marine_snow(buffers: FrameBuffers, params: MarineSnowParams, rng: np.random.Generator) -> np.ndarray:
    """Draw lit marine-snow particles in front of the scene.

    Args:
        buffers: the frame; uses ``rgb``, ``range_m`` and ``camera``.
        params: particle population, lamps and water.
        rng: the random generator; the same seed gives the same particles.

    Returns:
        (H, W, 3) float32 new image ``rgb + coverage * radiance`` (never darker than ``rgb``); pixels without a
        visible particle are unchanged.
    """
    particles = sample_particles(buffers, params, rng)
    if particles.range_m.size == 0:
        return buffers.rgb.copy()
    H, W = buffers.shape
    alpha, color = _splat(particles, clean_range(buffers.range_m), params)
    # Overlapping discs: total coverage capped at 1, their colours averaged by coverage.
    norm = np.where(alpha > 1.0, 1.0 / np.maximum(alpha, 1.0), 1.0)
    added = (color * norm[:, None]).astype(np.float32).reshape(H, W, 3)
    return buffers.rgb + added

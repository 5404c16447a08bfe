"""ROV-carried spot lamps: irradiance on the surfaces and the light they reflect.

The clean render is lit by the scene's ambient (down-welling) light only; this
effect adds the lamps. A lamp at ``offset_m`` (camera frame) with unit axis
``direction`` sends ``intensity * profile(angle) * exp(-beta_D d) / d^2`` to a
point at distance ``d`` (inverse-square falloff, attenuated along the
lamp-to-surface path); ``profile`` is 1 on the axis, 0 outside the cone
half-angle and a smoothstep over the outer ``edge_deg`` of the cone. Surfaces
are Lambertian: reflected radiance ``rho / pi * E * cos(incidence)``, with the
albedo ``rho`` estimated from the clean render as ``rgb / ambient``.

The surface-to-camera path is attenuated by the ``attenuation`` effect, which
runs right after this one and dims all surface radiance, lamp light included.
Set ``camera_path=True`` to attenuate it here instead (lamps used on their own).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cadalign.errors import ConfigError
from cadalign.sim.effects.attenuation import transmission
from cadalign.sim.effects.buffers import FrameBuffers, broadcast_channels, clean_range
from cadalign.sim.effects.water import WaterParams, water_from_jerlov

_MIN_LAMP_DIST_M = 1e-3
_MAX_LAMP_RANGE_M = np.float32(1e6)
"""Surfaces farther than this get the lamp light of this range (< 1e-12 of it at 1 m): keeps ``r^2`` finite."""


@dataclass(frozen=True)
class Lamp:
    """One spot lamp, fixed to the camera (same fields as the scene file's ``LightSpec``)."""

    offset_m: tuple[float, float, float] = (0.0, -0.3, 0.0)
    """Lamp position in the camera frame (x right, y down, z forward), metres."""
    direction: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """Lamp axis in the camera frame (normalised here)."""
    intensity: float = 40.0
    """Radiant intensity on the axis: irradiance at 1 m before attenuation, clean-render units."""
    cone_deg: float = 60.0
    """Half-angle of the cone, degrees; nothing is lit outside it."""
    edge_deg: float = 10.0
    """Width of the soft edge inside the cone, degrees (0: hard edge), capped at ``cone_deg``: scene-file lights
    have no edge field, so a cone narrower than the default edge is soft all through rather than refused."""

    def __post_init__(self) -> None:
        if np.linalg.norm(self.direction) == 0:
            raise ConfigError("Lamp.direction must be non-zero")
        if not self.intensity >= 0:
            raise ConfigError(f"Lamp.intensity must be >= 0, got {self.intensity}")
        if not 0 < self.cone_deg <= 90:
            raise ConfigError(f"Lamp.cone_deg must be in (0, 90], got {self.cone_deg}")
        if not self.edge_deg >= 0:
            raise ConfigError(f"Lamp.edge_deg must be >= 0, got {self.edge_deg}")


@dataclass(frozen=True)
class ArtificialLightParams:
    lamps: tuple[Lamp, ...] = (Lamp(offset_m=(-0.4, -0.2, 0.0)), Lamp(offset_m=(0.4, -0.2, 0.0)))
    """The ROV's lamps."""
    water: WaterParams = field(default_factory=lambda: water_from_jerlov("II"))
    """Water between lamps, surfaces and camera (``beta_D`` is used)."""
    ambient: float = 0.35
    """Ambient level of the clean render, to turn its colours into albedo (``rho = rgb / ambient``)."""
    camera_path: bool = False
    """Also attenuate the lamp light from surface to camera (leave False when ``attenuation`` runs)."""

    def __post_init__(self) -> None:
        if not self.ambient > 0:
            raise ConfigError(f"ArtificialLightParams.ambient must be > 0, got {self.ambient}")


def lamp_profile(cos_axis: np.ndarray, lamp: Lamp) -> np.ndarray:
    """Angular profile: 1 inside ``cone - edge``, smoothstep to 0 at the cone, 0 outside.

    Args:
        cos_axis: (...) cosine of the angle between the lamp axis and the direction to the point.
        lamp: the lamp.

    Returns:
        (...) float32 in [0, 1].
    """
    cos_out = np.float32(np.cos(np.radians(lamp.cone_deg)))
    cos_in = np.float32(np.cos(np.radians(lamp.cone_deg - min(lamp.edge_deg, lamp.cone_deg))))
    if cos_in <= cos_out:
        return (cos_axis >= cos_out).astype(np.float32)
    t = np.clip((cos_axis - cos_out) / (cos_in - cos_out), 0.0, 1.0)
    return (t * t * (np.float32(3.0) - np.float32(2.0) * t)).astype(np.float32)


def lamp_irradiance(rays: np.ndarray, range_m: np.ndarray, lamps: tuple[Lamp, ...], beta_D: np.ndarray,
                    normals_cam: np.ndarray | None = None) -> np.ndarray:
    """Irradiance from the lamps at the points ``range_m * rays`` (surfaces, or particles in the water).

    Works on the range along each unit ray, so the per-lamp work is a few (...)-shaped
    operations: ``|p - o|^2 = r^2 - 2 r (ray . o) + |o|^2``.

    Args:
        rays: (..., 3) float32 unit directions from the camera, camera frame.
        range_m: (...) float32 finite distances along the rays, metres.
        lamps: the lamps.
        beta_D: (3,) attenuation along the lamp-to-point path, 1/m.
        normals_cam: (..., 3) unit normals for Lambert's cosine; None = facing each lamp (cosine 1).

    Returns:
        (..., 3) float32 irradiance per R, G, B channel.
    """
    r = np.asarray(range_m, dtype=np.float32)
    E = np.zeros((*r.shape, 3), dtype=np.float32)
    flat = np.asarray(rays, dtype=np.float32).reshape(-1, 3)
    n_flat = None if normals_cam is None else np.asarray(normals_cam, dtype=np.float32).reshape(-1, 3)
    rn = None if n_flat is None else np.einsum("ij,ij->i", flat, n_flat).reshape(r.shape)
    for lamp in lamps:
        o = np.asarray(lamp.offset_m, dtype=np.float32)
        axis = np.asarray(lamp.direction, dtype=np.float32)
        axis /= np.linalg.norm(axis)
        ray_o, ray_axis = (flat @ np.stack([o, axis], axis=1)).T.reshape(2, *r.shape)
        d = np.sqrt(np.maximum(r * (r - 2 * ray_o) + np.float32(o @ o), np.float32(_MIN_LAMP_DIST_M**2)))
        inv_d = np.float32(1.0) / d
        scalar = lamp_profile((r * ray_axis - np.float32(o @ axis)) * inv_d, lamp)
        scalar *= np.float32(lamp.intensity) * inv_d * inv_d
        if n_flat is not None:
            n_o = (n_flat @ o).reshape(r.shape)
            scalar *= np.maximum((n_o - r * rn) * inv_d, np.float32(0.0))  # cos = -(p - o).n / d
        E += broadcast_channels(scalar) * transmission(d, beta_D)
    return E


def lamp_irradiance_at(points_cam: np.ndarray, lamps: tuple[Lamp, ...], beta_D: np.ndarray) -> np.ndarray:
    """Irradiance from the lamps at (N, 3) camera-frame points, each facing the lamps; (N, 3) float32."""
    points = np.asarray(points_cam, dtype=np.float32)
    r = np.linalg.norm(points, axis=-1)
    rays = points / np.maximum(r, np.float32(1e-9))[..., None]
    return lamp_irradiance(rays, r, lamps, beta_D)


def artificial_light(buffers: FrameBuffers, params: ArtificialLightParams) -> np.ndarray:
    """Add the light of the ROV's lamps reflected by Lambertian surfaces.

    Args:
        buffers: the frame; uses ``rgb``, ``range_m``, ``rays_cam`` and ``normals_cam``.
        params: lamps, water and the clean render's ambient level.

    Returns:
        (H, W, 3) float32 new image, ``rgb + rho / pi * E`` (open water unchanged).
    """
    hit = np.isfinite(buffers.range_m)
    if not params.lamps or not hit.any():
        return buffers.rgb.copy()
    r = np.where(hit, np.minimum(clean_range(buffers.range_m), _MAX_LAMP_RANGE_M), np.float32(0.0))
    E = lamp_irradiance(buffers.rays_cam, r, params.lamps, params.water.beta_D, buffers.normals_cam)
    # rho / pi * E with the albedo rho = min(rgb / ambient, 1); no lamp light where there is no surface.
    E *= broadcast_channels(hit.astype(np.float32) * np.float32(1.0 / (np.pi * params.ambient)))
    added = np.clip(buffers.rgb, np.float32(0.0), np.float32(params.ambient)) * E
    if params.camera_path:
        added *= transmission(buffers.range_m, params.water.beta_D)
    return buffers.rgb + added

"""Underwater image-formation effects applied to clean renders.

Each effect is a pure function of a :class:`FrameBuffers` and its own frozen
params dataclass that returns a new image; :func:`apply_effects` runs the
effects a scene declares, and only those, in physical order.
"""

from cadalign.sim.effects.attenuation import AttenuationParams, attenuation, transmission
from cadalign.sim.effects.backscatter import BackscatterParams, backscatter
from cadalign.sim.effects.buffers import FrameBuffers, buffers_from_range, clean_range, pixel_rays_unit
from cadalign.sim.effects.forward_scatter import ForwardScatterParams, forward_scatter
from cadalign.sim.effects.lights import ArtificialLightParams, Lamp, artificial_light, lamp_irradiance_at
from cadalign.sim.effects.low_light import LowLightParams, low_light, noise_std
from cadalign.sim.effects.marine_snow import MarineSnowParams, Particles, marine_snow, sample_particles
from cadalign.sim.effects.motion_blur import MotionBlurParams, depth_flow, motion_blur, shutter_poses
from cadalign.sim.effects.pipeline import EFFECTS, EffectSpec, apply_effects
from cadalign.sim.effects.vignetting import VignettingParams, vignetting, vignetting_gain
from cadalign.sim.effects.water import JERLOV_TYPES, WaterParams, jerlov_table, water_from_jerlov

__all__ = [
    "EFFECTS", "JERLOV_TYPES", "ArtificialLightParams", "AttenuationParams", "BackscatterParams", "EffectSpec",
    "ForwardScatterParams", "FrameBuffers", "Lamp", "LowLightParams", "MarineSnowParams", "MotionBlurParams",
    "Particles", "VignettingParams", "WaterParams", "apply_effects", "artificial_light", "attenuation",
    "backscatter", "buffers_from_range", "clean_range", "depth_flow", "forward_scatter", "jerlov_table",
    "lamp_irradiance_at", "low_light", "marine_snow", "motion_blur", "noise_std", "pixel_rays_unit",
    "sample_particles", "shutter_poses", "transmission", "vignetting", "vignetting_gain", "water_from_jerlov",
]

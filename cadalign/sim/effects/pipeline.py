"""Run the declared water effects on a frame, in physical order.

Only the effects named in the scene's ``effects`` list run; an effect that is
not listed is never called and costs nothing. Whatever the order of the list,
they run in :data:`EFFECTS` order, the order light meets them on its way to the
sensor: ROV lamps, attenuation, forward scatter, backscatter, marine snow,
motion blur, vignetting, low light (exposure and sensor noise).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from cadalign.errors import ConfigError
from cadalign.sim.effects.attenuation import AttenuationParams, attenuation
from cadalign.sim.effects.backscatter import BackscatterParams, backscatter
from cadalign.sim.effects.buffers import FrameBuffers
from cadalign.sim.effects.forward_scatter import ForwardScatterParams, forward_scatter
from cadalign.sim.effects.lights import ArtificialLightParams, artificial_light
from cadalign.sim.effects.low_light import LowLightParams, low_light
from cadalign.sim.effects.marine_snow import MarineSnowParams, marine_snow
from cadalign.sim.effects.motion_blur import MotionBlurParams, motion_blur
from cadalign.sim.effects.vignetting import VignettingParams, vignetting


@dataclass(frozen=True)
class EffectSpec:
    """One registered effect.

    Attributes:
        params_type: its frozen params dataclass (every field has a default).
        fn: ``fn(buffers, params) -> rgb``, or ``fn(buffers, params, rng) -> rgb`` when ``uses_rng``.
        uses_rng: whether it draws random numbers.
    """

    params_type: type
    fn: Callable[..., np.ndarray]
    uses_rng: bool = False


EFFECTS: dict[str, EffectSpec] = {
    "artificial_light": EffectSpec(ArtificialLightParams, artificial_light),
    "attenuation": EffectSpec(AttenuationParams, attenuation),
    "forward_scatter": EffectSpec(ForwardScatterParams, forward_scatter),
    "backscatter": EffectSpec(BackscatterParams, backscatter),
    "marine_snow": EffectSpec(MarineSnowParams, marine_snow, uses_rng=True),
    "motion_blur": EffectSpec(MotionBlurParams, motion_blur),
    "vignetting": EffectSpec(VignettingParams, vignetting),
    "low_light": EffectSpec(LowLightParams, low_light, uses_rng=True),
}
"""Effect name -> spec, in the fixed physical order they are applied."""


def _resolve(effects: Sequence[tuple[str, Any]]) -> list[tuple[str, Any]]:
    """Check names and params types, fill defaults for None params and sort into physical order."""
    seen: dict[str, Any] = {}
    for name, params in effects:
        spec = EFFECTS.get(name)
        if spec is None:
            raise ConfigError(f"unknown effect {name!r}; allowed values: {', '.join(EFFECTS)}")
        if name in seen:
            raise ConfigError(f"effect {name!r} is listed twice; list each effect once")
        if params is None:
            params = spec.params_type()
        elif not isinstance(params, spec.params_type):
            raise ConfigError(f"effect {name!r} needs {spec.params_type.__name__}, got {type(params).__name__}")
        seen[name] = params
    return [(name, seen[name]) for name in EFFECTS if name in seen]


def apply_effects(buffers: FrameBuffers, effects: Sequence[tuple[str, Any]],
                  rng: np.random.Generator) -> tuple[np.ndarray, dict[str, float]]:
    """Apply the listed effects to the frame, each exactly once, in physical order.

    Args:
        buffers: the rendered frame.
        effects: ``(name, params)`` pairs; params None = that effect's defaults. Names must be keys of
            :data:`EFFECTS`. Only these effects are run.
        rng: random generator for the stochastic effects (marine snow, sensor noise).

    Returns:
        The (H, W, 3) float32 image, clipped to [0, 1] like a saturating sensor, and the seconds spent
        per effect. With no effects: ``buffers.rgb`` itself (the same object) and ``{}``.

    Raises:
        ConfigError: unknown or repeated effect name, or params of the wrong type.
    """
    plan = _resolve(effects)
    if not plan:
        return buffers.rgb, {}
    timings: dict[str, float] = {}
    current = buffers
    for name, params in plan:
        spec = EFFECTS[name]
        t0 = time.perf_counter()
        rgb = spec.fn(current, params, rng) if spec.uses_rng else spec.fn(current, params)
        timings[name] = time.perf_counter() - t0
        current = dataclasses.replace(current, rgb=rgb)
    return np.clip(current.rgb, 0.0, 1.0), timings

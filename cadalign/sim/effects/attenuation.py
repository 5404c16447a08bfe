"""Attenuation of the direct signal along the line of sight: ``J exp(-beta_D z)``."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cadalign.sim.effects.buffers import FrameBuffers, clean_range, per_channel
from cadalign.sim.effects.water import WaterParams, water_from_jerlov


@dataclass(frozen=True)
class AttenuationParams:
    water: WaterParams = field(default_factory=lambda: water_from_jerlov("II"))
    """Water coefficients; only ``beta_D`` is used here."""


def transmission(range_m: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Per-channel transmittance ``exp(-beta z)`` without NaN from ``0 * inf``.

    Args:
        range_m: (...) ranges in metres (inf/NaN: open water, negative: 0).
        beta: (3,) attenuation coefficients, 1/m.

    Returns:
        (..., 3) float32 in [0, 1]; exactly 1 at range 0 and exactly 0 at infinite range when beta > 0.
    """
    z = clean_range(range_m)
    return per_channel([np.exp(z * np.float32(-b)) for b in np.asarray(beta, dtype=np.float32)])


def attenuation(buffers: FrameBuffers, params: AttenuationParams) -> np.ndarray:
    """Attenuate the direct signal: ``J_c exp(-beta_D_c z)`` with z the range (Akkaynak & Treibitz 2018).

    Args:
        buffers: the frame; uses ``rgb`` and ``range_m``.
        params: the water.

    Returns:
        (H, W, 3) float32 new image; open-water pixels (no surface) go to 0 when beta_D > 0.
    """
    return buffers.rgb * transmission(buffers.range_m, params.water.beta_D)

"""Backscatter (veiling light) added along the line of sight: ``B_inf (1 - exp(-beta_B z))``."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from cadalign.sim.effects.buffers import FrameBuffers, clean_range, open_water_mask, per_channel
from cadalign.sim.effects.water import WaterParams, water_from_jerlov


@dataclass(frozen=True)
class BackscatterParams:
    water: WaterParams = field(default_factory=lambda: water_from_jerlov("II"))
    """Water coefficients; ``beta_B`` and ``B_inf`` are used here."""


def veiling_light(range_m: np.ndarray, water: WaterParams) -> np.ndarray:
    """Backscatter ``B_inf_c (1 - exp(-beta_B_c z))`` per pixel and channel.

    Args:
        range_m: (H, W) ranges in metres (inf/NaN: open water).
        water: the water.

    Returns:
        (H, W, 3) float32, 0 at range 0, ``B_inf`` at infinite range (for beta_B > 0).
    """
    z = clean_range(range_m)
    one = np.float32(1.0)
    planes = [np.float32(B) * (one - np.exp(z * np.float32(-beta)))
              for B, beta in zip(water.B_inf, water.beta_B, strict=True)]
    return per_channel(planes)


def backscatter(buffers: FrameBuffers, params: BackscatterParams) -> np.ndarray:
    """Add backscatter ``B_inf_c (1 - exp(-beta_B_c z))``; open water becomes exactly ``B_inf``.

    The direct signal is left to :func:`~cadalign.sim.effects.attenuation.attenuation`
    (``beta_D != beta_B`` in the revised model). A pixel with no surface (range inf or
    NaN) sees only veiling light, so it is set to ``B_inf`` whatever its input.

    Args:
        buffers: the frame; uses ``rgb`` and ``range_m``.
        params: the water.

    Returns:
        (H, W, 3) float32 new image.
    """
    out = buffers.rgb + veiling_light(buffers.range_m, params.water)
    out[open_water_mask(buffers.range_m)] = params.water.B_inf
    return out

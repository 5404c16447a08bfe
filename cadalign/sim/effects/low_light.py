"""Low light: exposure, sensor gain and noise, and quantisation.

Sensor model (Gaussian approximation of Poisson shot noise, per pixel and
channel)::

    s   = exposure * rgb                        # fraction of full well collected
    N   = s * full_well_e                       # photo-electrons
    out = gain * (N + sqrt(N + read_noise_e^2) * n) / full_well_e,  n ~ N(0, 1)

so ``E[out] = gain * exposure * rgb`` and ``Var[out] = gain * E[out] / full_well_e
+ (gain * read_noise_e / full_well_e)^2``: one output level holds
``full_well_e / gain`` electrons, and pushing the gain up to brighten a dark
exposure makes the picture noisier. The result is clipped to [0, 1] and
quantised to ``2^bits - 1`` levels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cadalign.errors import ConfigError
from cadalign.sim.effects.buffers import FrameBuffers


@dataclass(frozen=True)
class LowLightParams:
    exposure: float = 0.25
    """Light collected relative to a normal exposure (shorter shutter, darker scene), > 0."""
    gain: float = 4.0
    """Analogue gain (ISO relative to base ISO), > 0; ``gain * exposure = 1`` keeps the brightness."""
    full_well_e: float = 6000.0
    """Photo-electrons at full scale with gain 1."""
    read_noise_e: float = 4.0
    """Read noise, electrons (standard deviation)."""
    bits: int | None = 8
    """Output quantisation in bits; None keeps continuous values."""

    def __post_init__(self) -> None:
        checks = {"exposure": self.exposure > 0, "gain": self.gain > 0, "full_well_e": self.full_well_e > 0,
                  "read_noise_e": self.read_noise_e >= 0, "bits": self.bits is None or 1 <= self.bits <= 24}
        bad = [name for name, ok in checks.items() if not ok]
        if bad:
            raise ConfigError(f"LowLightParams: invalid {', '.join(f'{n}={getattr(self, n)!r}' for n in bad)}")


def noise_std(mean_out: np.ndarray, params: LowLightParams) -> np.ndarray:
    """Standard deviation of the output for a given expected output (before clipping and quantisation).

    Args:
        mean_out: (...) expected output ``gain * exposure * rgb``.
        params: the sensor.

    Returns:
        (...) float32 standard deviation, output units.
    """
    g_fw = np.float32(params.gain / params.full_well_e)
    read = np.float32(params.read_noise_e * params.gain / params.full_well_e)
    return np.sqrt(np.maximum(mean_out, np.float32(0.0)) * g_fw + read * read)


def low_light(buffers: FrameBuffers, params: LowLightParams, rng: np.random.Generator) -> np.ndarray:
    """Expose, amplify, add shot and read noise, clip to [0, 1] and quantise.

    Args:
        buffers: the frame; uses ``rgb``.
        params: exposure, gain and noise of the sensor.
        rng: the random generator (the only source of randomness).

    Returns:
        (H, W, 3) float32 new image in [0, 1].
    """
    mean = buffers.rgb * np.float32(params.exposure * params.gain)
    noise = rng.standard_normal(mean.shape, dtype=np.float32)
    out = mean + noise_std(mean, params) * noise
    np.clip(out, 0.0, 1.0, out=out)
    if params.bits is not None:
        levels = np.float32(2**params.bits - 1)
        out = np.rint(out * levels) / levels
    return out

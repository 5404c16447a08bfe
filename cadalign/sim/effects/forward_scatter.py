"""Forward scattering: a blur whose width grows with range.

Light from a surface point that is scattered through small angles still reaches
the camera, but from slightly wrong directions, so distant surfaces look soft.
The point-spread function is modelled as a Gaussian of standard deviation
``sigma_px = fx * sigma_mrad_per_m * 1e-3 * z`` (capped). For bounded cost the image
is blurred once per level of a small fixed ladder (``LEVELS_PX``, wide levels
computed at reduced resolution) and each pixel blends the two levels around its
own sigma with weights linear in sigma^2, so the blended PSF has exactly the
model's variance (weights linear in sigma would, e.g., turn a 0.5 px blur into a
0.7 px one: half the sharp image plus half the 1 px level).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cadalign.errors import ConfigError
from cadalign.sim.effects.buffers import FrameBuffers, clean_range

LEVELS_PX: tuple[float, ...] = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0)
"""Blur ladder (Gaussian sigma, pixels); level 0 is the sharp image."""
_FULL_RES_MAX_SIGMA = 2.5


@dataclass(frozen=True)
class ForwardScatterParams:
    sigma_mrad_per_m: float = 1.5
    """Angular spread of the forward-scattering PSF per metre of range, milliradians (turbid water: larger)."""
    max_sigma_px: float = 8.0
    """Largest blur, pixels (at most the top of ``LEVELS_PX``); open water gets it."""

    def __post_init__(self) -> None:
        if not self.sigma_mrad_per_m >= 0:
            raise ConfigError(f"ForwardScatterParams.sigma_mrad_per_m must be >= 0, got {self.sigma_mrad_per_m}")
        if not 0 <= self.max_sigma_px <= LEVELS_PX[-1]:
            raise ConfigError(f"ForwardScatterParams.max_sigma_px must be in [0, {LEVELS_PX[-1]}], "
                              f"got {self.max_sigma_px}")


def gaussian_blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur; wide blurs run on a 2^k-downsampled copy and are resized back.

    Args:
        img: (H, W, C) float32 image.
        sigma_px: standard deviation in full-resolution pixels.

    Returns:
        (H, W, C) float32 blurred image.
    """
    if sigma_px <= 0:
        return img.copy()
    H, W = img.shape[:2]
    scale = 1
    while sigma_px / scale > _FULL_RES_MAX_SIGMA and min(H, W) // (2 * scale) >= 8:
        scale *= 2
    small = img if scale == 1 else cv2.resize(img, (W // scale, H // scale), interpolation=cv2.INTER_AREA)
    # INTER_AREA already averages over `scale` px (a box of variance scale^2/12); blur only the remainder.
    residual = np.sqrt(max(sigma_px**2 - (scale**2 - 1) / 12.0, 0.0)) / scale
    blurred = cv2.GaussianBlur(small, (0, 0), residual, borderType=cv2.BORDER_REFLECT) if residual > 0 else small
    if scale == 1:
        return blurred
    return cv2.resize(blurred, (W, H), interpolation=cv2.INTER_LINEAR)


def range_sigma_px(buffers: FrameBuffers, params: ForwardScatterParams) -> np.ndarray:
    """(H, W) float32 per-pixel blur sigma in pixels (open water: ``max_sigma_px``)."""
    gain = np.float32(buffers.camera.fx * params.sigma_mrad_per_m * 1e-3)
    return np.minimum(clean_range(buffers.range_m) * gain, np.float32(params.max_sigma_px))


def forward_scatter(buffers: FrameBuffers, params: ForwardScatterParams) -> np.ndarray:
    """Blur each pixel by a Gaussian whose sigma grows linearly with its range.

    Args:
        buffers: the frame; uses ``rgb``, ``range_m`` and ``camera.fx``.
        params: PSF growth and cap.

    Returns:
        (H, W, 3) float32 new image; identical to the input where the range is 0.
    """
    rgb = buffers.rgb
    sigma = range_sigma_px(buffers, params)
    top = float(sigma.max()) if sigma.size else 0.0
    if top <= 0:
        return rgb.copy()
    n_levels = int(np.searchsorted(LEVELS_PX, top)) + 1  # levels up to the first one >= top
    levels = np.asarray(LEVELS_PX[:n_levels], dtype=np.float32)
    # Blend weights linear in variance: (1 - w) a^2 + w b^2 = sigma^2 between levels a and b.
    pos = np.interp(sigma * sigma, levels * levels, np.arange(n_levels, dtype=np.float32)).astype(np.float32)
    out = np.zeros_like(rgb)
    for k in range(n_levels):
        w = np.maximum(np.float32(1.0) - np.abs(pos - np.float32(k)), np.float32(0.0))
        if not w.any():
            continue
        level = rgb if k == 0 else gaussian_blur(rgb, float(levels[k]))
        out += level * w[..., None]
    return out

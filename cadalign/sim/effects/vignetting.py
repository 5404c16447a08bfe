"""Vignetting: brightness falling off towards the image corners."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from cadalign.errors import ConfigError
from cadalign.sim.effects.buffers import FrameBuffers
from cadalign.types import Camera


@dataclass(frozen=True)
class VignettingParams:
    model: Literal["cos4", "poly"] = "cos4"
    """cos4: natural falloff ``cos(theta)^exponent`` of the off-axis angle theta;
    poly: ``1 + k1 r^2 + k2 r^4 + k3 r^6`` with r the distance from the principal point over the half-diagonal."""
    exponent: float = 4.0
    """cos4 model: the power of cos(theta)."""
    coeffs: tuple[float, float, float] = (-0.3, 0.0, 0.0)
    """poly model: (k1, k2, k3)."""

    def __post_init__(self) -> None:
        if self.model not in ("cos4", "poly"):
            raise ConfigError(f"VignettingParams.model must be 'cos4' or 'poly', got {self.model!r}")
        if not self.exponent >= 0:
            raise ConfigError(f"VignettingParams.exponent must be >= 0, got {self.exponent}")


def vignetting_gain(camera: Camera, params: VignettingParams) -> np.ndarray:
    """Per-pixel brightness factor, 1 at the principal point.

    Args:
        camera: the camera (pixel centres at ``u + 0.5``).
        params: the falloff model.

    Returns:
        (H, W) float32 factor, clipped to >= 0.
    """
    u = np.arange(camera.width, dtype=np.float32) + np.float32(0.5 - camera.cx)
    v = np.arange(camera.height, dtype=np.float32) + np.float32(0.5 - camera.cy)
    if params.model == "cos4":
        x2 = (u / np.float32(camera.fx)) ** 2
        y2 = (v / np.float32(camera.fy)) ** 2
        cos2 = np.float32(1.0) / (np.float32(1.0) + x2[None, :] + y2[:, None])
        return (cos2 ** np.float32(params.exponent / 2)).astype(np.float32)
    half_diag2 = np.float32((camera.width**2 + camera.height**2) / 4.0)
    r2 = (u[None, :] ** 2 + v[:, None] ** 2) / half_diag2
    k1, k2, k3 = (np.float32(k) for k in params.coeffs)
    return np.maximum(np.float32(1.0) + r2 * (k1 + r2 * (k2 + r2 * k3)), np.float32(0.0))


def vignetting(buffers: FrameBuffers, params: VignettingParams) -> np.ndarray:
    """Darken the image towards its corners.

    Args:
        buffers: the frame; uses ``rgb`` and ``camera``.
        params: the falloff model.

    Returns:
        (H, W, 3) float32 new image.
    """
    return buffers.rgb * vignetting_gain(buffers.camera, params)[..., None]

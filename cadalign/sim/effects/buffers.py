"""Per-frame inputs shared by the water effects.

Frames are camera-frame (x right, y down, z forward), metres. Pixel ``(u, v)``
covers ``[u, u+1)`` with its centre at ``u + 0.5`` (see :mod:`cadalign.types`).
Open water (no surface along a pixel's ray) has ``range_m = inf``; a NaN range
is treated as open water too, and a negative one as 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cadalign.errors import InputError
from cadalign.types import Camera, Rigid3

OPEN_WATER_M = np.float32(1e30)
"""Finite stand-in for an infinite range: ``exp(-beta * 1e30)`` is exactly 0 for beta > 0 and 1 for beta = 0,
where ``beta * inf`` would give NaN."""


@dataclass(frozen=True)
class FrameBuffers:
    """What the renderer hands the effects for one frame (H×W pixels).

    Attributes:
        rgb: (H, W, 3) float32 linear radiance of the clean render, nominally in [0, 1].
        depth_m: (H, W) z-depth in metres; 0 or inf where there is no surface.
        range_m: (H, W) Euclidean camera-to-surface distance in metres; inf for open water.
        rays_cam: (H, W, 3) unit ray directions through the pixel centres, camera frame.
        normals_cam: (H, W, 3) unit surface normals facing the camera, camera frame; 0 for open water.
        camera: the pinhole camera (K, width, height).
        T_world_from_cam: camera pose at the frame time.
        T_world_from_cam_prev: camera pose one frame earlier (None: unknown, taken as not moving).
        T_world_from_cam_next: camera pose one frame later (None: unknown, taken as not moving).
        frame_dt_s: time between consecutive frames, seconds (0: no motion information).
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    range_m: np.ndarray
    rays_cam: np.ndarray
    normals_cam: np.ndarray
    camera: Camera
    T_world_from_cam: Rigid3 = Rigid3()
    T_world_from_cam_prev: Rigid3 | None = None
    T_world_from_cam_next: Rigid3 | None = None
    frame_dt_s: float = 0.0

    def __post_init__(self) -> None:
        if getattr(self.rgb, "dtype", None) != np.float32:
            object.__setattr__(self, "rgb", np.asarray(self.rgb, dtype=np.float32))
        H, W = self.camera.height, self.camera.width
        expected = {"rgb": (H, W, 3), "depth_m": (H, W), "range_m": (H, W), "rays_cam": (H, W, 3),
                    "normals_cam": (H, W, 3)}
        for name, shape in expected.items():
            got = getattr(self, name).shape
            if got != shape:
                raise InputError(f"FrameBuffers.{name} must have shape {shape} for a {W}x{H} camera, got {got}")
        if not self.frame_dt_s >= 0.0:
            raise InputError(f"FrameBuffers.frame_dt_s must be >= 0, got {self.frame_dt_s}")

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) image size."""
        return self.camera.height, self.camera.width


def pixel_rays_unit(camera: Camera) -> np.ndarray:
    """Unit camera-frame rays through the pixel centres.

    Args:
        camera: the pinhole camera.

    Returns:
        (H, W, 3) float32 unit directions ``normalise(K^-1 (u + 0.5, v + 0.5, 1))``.
    """
    x = (np.arange(camera.width, dtype=np.float64) + 0.5 - camera.cx) / camera.fx
    y = (np.arange(camera.height, dtype=np.float64) + 0.5 - camera.cy) / camera.fy
    xx, yy = np.meshgrid(x, y)
    d = np.stack([xx, yy, np.ones_like(xx)], axis=-1)
    return (d / np.linalg.norm(d, axis=-1, keepdims=True)).astype(np.float32)


def buffers_from_range(rgb: np.ndarray, range_m: np.ndarray, camera: Camera,
                       normals_cam: np.ndarray | None = None, **poses: object) -> FrameBuffers:
    """Build :class:`FrameBuffers` from an image and a range map (for tests and notebooks).

    Args:
        rgb: (H, W, 3) linear radiance.
        range_m: (H, W) camera-to-surface distance in metres (inf: open water).
        camera: the pinhole camera.
        normals_cam: (H, W, 3) normals; None = every surface faces the camera (``-ray``).
        **poses: optional ``T_world_from_cam``, ``T_world_from_cam_prev``, ``T_world_from_cam_next``,
            ``frame_dt_s``.

    Returns:
        The frame buffers, with ``depth_m = range * ray_z`` (0 for open water).
    """
    rays = pixel_rays_unit(camera)
    rng_m = np.asarray(range_m, dtype=np.float32)
    with np.errstate(invalid="ignore"):
        hit = np.isfinite(rng_m)
        depth = np.where(hit, rng_m * rays[..., 2], 0.0).astype(np.float32)
    if normals_cam is None:
        normals_cam = np.where(hit[..., None], -rays, 0.0).astype(np.float32)
    return FrameBuffers(np.asarray(rgb, dtype=np.float32), depth, rng_m, rays, normals_cam, camera, **poses)


def clean_range(range_m: np.ndarray) -> np.ndarray:
    """Ranges safe for ``exp(-beta * z)``: NaN and inf become :data:`OPEN_WATER_M`, negatives 0.

    Finite ranges beyond :data:`OPEN_WATER_M` (float64 input too large for float32) are capped at it,
    so ``beta * z`` cannot overflow for any plausible beta (< 3e8 per metre).

    Args:
        range_m: (H, W) ranges in metres.

    Returns:
        (H, W) float32 finite ranges in ``[0, OPEN_WATER_M]``.
    """
    with np.errstate(over="ignore"):  # a float64 range beyond float32's reach casts to inf, handled below
        z = np.asarray(range_m, dtype=np.float32)
    z = np.where(np.isfinite(z), z, OPEN_WATER_M)
    return np.clip(z, np.float32(0.0), OPEN_WATER_M)


def open_water_mask(range_m: np.ndarray) -> np.ndarray:
    """(H, W) bool: True where the ray meets no surface (range inf or NaN)."""
    return ~np.isfinite(range_m)


def per_channel(planes: list[np.ndarray]) -> np.ndarray:
    """Interleave three same-shape float32 planes into a (..., 3) array.

    Numpy is slow at broadcasting against a length-3 last axis, so effects compute
    per channel on (H, W) planes and interleave once (``cv2.merge`` for images).

    Args:
        planes: three (...) float32 arrays, R, G, B.

    Returns:
        (..., 3) float32 array.
    """
    if planes[0].ndim == 2 and all(p.dtype == np.float32 for p in planes):
        return cv2.merge([np.ascontiguousarray(p) for p in planes])
    return np.stack(planes, axis=-1).astype(np.float32, copy=False)


def broadcast_channels(plane: np.ndarray) -> np.ndarray:
    """(..., 3) float32 copy of a (...) plane in every channel (to scale an image per pixel)."""
    p = np.asarray(plane, dtype=np.float32)
    return per_channel([p, p, p])

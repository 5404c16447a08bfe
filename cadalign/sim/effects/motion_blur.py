"""Motion blur from the camera's own motion during the exposure.

Approximation: the frame is rendered at the mid-exposure pose. For the poses at
shutter open and close the per-pixel image motion ("flow") of every surface
point is computed exactly from its range (open water: a point at infinity, so
rotation only). In between, flow is interpolated linearly, and the image seen
at each of ``n_samples`` instants is obtained by backward-warping the rendered
frame with ``cv2.remap``, reading the flow at the destination pixel instead of
the source (first order in the motion). The samples are averaged. Not modelled:
disocclusions (uncovered background is stretched from its neighbours), moving
objects, rolling shutter. Adequate while the motion during the exposure is a few
pixels to a few tens of pixels.

The shutter poses are interpolated (slerp and lerp) between the frame's pose and
its neighbours, ``shutter_s / 2`` before and after the frame time.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from cadalign.errors import ConfigError
from cadalign.sim.effects.buffers import FrameBuffers
from cadalign.types import Rigid3

_NEAR_M = 0.05
_STILL_PX = 1e-4


@dataclass(frozen=True)
class MotionBlurParams:
    shutter_s: float = 0.02
    """Exposure time, seconds."""
    n_samples: int = 6
    """Instants averaged over the exposure (cost grows linearly)."""

    def __post_init__(self) -> None:
        if not self.shutter_s >= 0:
            raise ConfigError(f"MotionBlurParams.shutter_s must be >= 0, got {self.shutter_s}")
        if not 1 <= self.n_samples <= 64:
            raise ConfigError(f"MotionBlurParams.n_samples must be in [1, 64], got {self.n_samples}")


def interpolate_pose(T_a: Rigid3, T_b: Rigid3, s: float) -> Rigid3:
    """Pose a fraction ``s`` of the way from ``T_a`` to ``T_b`` (slerp rotation, lerp translation)."""
    rotvec = Rotation.from_matrix(T_a.R.T @ T_b.R).as_rotvec()
    R = T_a.R @ Rotation.from_rotvec(s * rotvec).as_matrix()
    return Rigid3(R, (1.0 - s) * T_a.t + s * T_b.t)


def shutter_poses(buffers: FrameBuffers, shutter_s: float) -> tuple[Rigid3, Rigid3]:
    """``T_world_from_cam`` at shutter open and close; a missing neighbour means no motion on that side.

    The exposure is centred on the frame time and cannot extend past the neighbouring frames.
    """
    T = buffers.T_world_from_cam
    if buffers.frame_dt_s <= 0 or shutter_s <= 0:
        return T, T
    s = min(0.5 * shutter_s / buffers.frame_dt_s, 1.0)
    prev, nxt = buffers.T_world_from_cam_prev, buffers.T_world_from_cam_next
    T_open = T if prev is None else interpolate_pose(T, prev, s)
    T_close = T if nxt is None else interpolate_pose(T, nxt, s)
    return T_open, T_close


def _same_pose(T_a: Rigid3, T_b: Rigid3) -> bool:
    return bool(np.array_equal(T_a.R, T_b.R) and np.array_equal(T_a.t, T_b.t))


def depth_flow(buffers: FrameBuffers, T_other_from_cam: Rigid3) -> tuple[np.ndarray, np.ndarray]:
    """Image motion of each pixel's surface point when the camera moves to another pose.

    Args:
        buffers: the frame; uses ``rays_cam``, ``range_m`` and ``camera``.
        T_other_from_cam: maps this frame's camera coordinates into the other camera's.

    Returns:
        (H, W) float32 du and (H, W) float32 dv, pixels; open water moves with the rotation only.
    """
    cam = buffers.camera
    r = buffers.range_m
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_r = np.where(np.isfinite(r), np.float32(1.0) / np.maximum(r, np.float32(_NEAR_M)), np.float32(0.0))
    # A point r * d maps to R (r d) + t, which projects like R d + t / r (so infinity is exact).
    H, W = buffers.shape
    a = (buffers.rays_cam.reshape(-1, 3) @ T_other_from_cam.R.T.astype(np.float32)).reshape(H, W, 3)
    t = T_other_from_cam.t.astype(np.float32)
    ax, ay, az = (a[..., i] + t[i] * inv_r for i in range(3))
    inv_z = np.float32(1.0) / np.maximum(az, np.float32(1e-6))
    # Flow relative to the reprojection of the unmoved ray (not the pixel grid): float32 rounding of the
    # unit rays then cancels, so an identity motion gives exactly zero flow at any image size.
    d = buffers.rays_cam
    inv_dz = np.float32(1.0) / np.maximum(d[..., 2], np.float32(1e-6))
    du = np.float32(cam.fx) * (ax * inv_z - d[..., 0] * inv_dz)
    dv = np.float32(cam.fy) * (ay * inv_z - d[..., 1] * inv_dz)
    return du.astype(np.float32), dv.astype(np.float32)


def motion_blur(buffers: FrameBuffers, params: MotionBlurParams) -> np.ndarray:
    """Average the frame over the camera motion during the exposure (see the module docstring).

    Args:
        buffers: the frame; uses ``rgb``, ``rays_cam``, ``range_m``, ``camera``, the poses and ``frame_dt_s``.
        params: shutter time and number of samples.

    Returns:
        (H, W, 3) float32 new image; an exact copy when the camera does not move.
    """
    T_open, T_close = shutter_poses(buffers, params.shutter_s)
    if _same_pose(T_open, buffers.T_world_from_cam) and _same_pose(T_close, buffers.T_world_from_cam):
        return buffers.rgb.copy()
    flows = [depth_flow(buffers, T.inverse() @ buffers.T_world_from_cam) for T in (T_open, T_close)]
    if max(float(np.abs(f).max()) for pair in flows for f in pair) < _STILL_PX:
        return buffers.rgb.copy()
    H, W = buffers.shape
    # Backward maps in cv2's convention (pixel centres at integers): source = destination - flow.
    gx = np.arange(W, dtype=np.float32)[None, :]
    gy = np.arange(H, dtype=np.float32)[:, None]
    (mx0, my0), (mx1, my1) = ((gx - du, gy - dv) for du, dv in flows)
    acc = np.zeros_like(buffers.rgb)
    for k in range(params.n_samples):
        tau = np.float32((k + 0.5) / params.n_samples)
        map_x = mx0 + tau * (mx1 - mx0)
        map_y = my0 + tau * (my1 - my0)
        acc += cv2.remap(buffers.rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return acc * np.float32(1.0 / params.n_samples)

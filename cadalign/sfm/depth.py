"""Semi-dense SfM depth maps: the sparse 3D points a frame observes, projected into it.

Only points the frame actually observes (its COLMAP track elements) are used,
so occluded points never leak into a depth map. A point lands in the pixel
containing its projection; pixel ``(u, v)`` covers ``[u, u+1) x [v, v+1)`` (the
cadalign / COLMAP convention), so the pixel index is ``floor`` of the projected
coordinate. Where several points land in one pixel the nearest wins. Depth is
the z coordinate in the camera frame, in SfM units (the model's arbitrary
scale); invalid pixels are 0. The dataset builder rescales these maps with the
CAD alignment's scale.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def splat_depth(
    uv: np.ndarray, z: np.ndarray, width: int, height: int, radius_px: int = 0
) -> np.ndarray:
    """Rasterise points with pixel coordinates ``uv`` and depths ``z`` into an (H, W) float32 map.

    Args:
        uv: (N, 2) continuous pixel coordinates (x right, y down; pixel (0, 0) covers [0, 1)^2).
        z: (N,) depths > 0; points with z <= 0 or outside the image are dropped.
        width: image width in pixels.
        height: image height in pixels.
        radius_px: fill a (2r+1)^2 square around each point's pixel (nearest depth wins).

    Returns:
        (height, width) float32 depth, 0 where no point landed.

    Example:
        >>> d = splat_depth(np.array([[2.7, 1.2]]), np.array([5.0]), 4, 3)
        >>> float(d[1, 2]), int((d > 0).sum())
        (5.0, 1)
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    if uv.shape[0] != z.shape[0]:
        raise ValueError(f"uv has {uv.shape[0]} points but z has {z.shape[0]}")
    depth = np.full(height * width, np.inf)
    ij = np.floor(uv).astype(np.int64)
    keep = (z > 0) & np.isfinite(z) & np.all(np.isfinite(uv), axis=1)
    for dy in range(-radius_px, radius_px + 1):
        for dx in range(-radius_px, radius_px + 1):
            x, y = ij[:, 0] + dx, ij[:, 1] + dy
            ok = keep & (x >= 0) & (x < width) & (y >= 0) & (y < height)
            np.minimum.at(depth, y[ok] * width + x[ok], z[ok])  # nearest point wins
    depth[~np.isfinite(depth)] = 0.0
    return depth.reshape(height, width).astype(np.float32)


def frame_points(rec: Any, image_id: int, min_track_length: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """The observed 3D points of one registered image in its camera frame and their projections.

    Args:
        rec: a pycolmap Reconstruction.
        image_id: a registered image of ``rec``.
        min_track_length: skip points seen in fewer frames.

    Returns:
        ``(uv (N, 2) projected pixel coordinates, xyz_cam (N, 3) points in the camera frame, SfM units)``.
    """
    image = rec.images[image_id]
    ids = [p.point3D_id for p in image.points2D if p.has_point3D()]
    ids = [i for i in dict.fromkeys(ids) if rec.points3D[i].track.length() >= min_track_length]
    if not ids:
        return np.zeros((0, 2)), np.zeros((0, 3))
    xyz = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64)
    T = image.cam_from_world()
    xyz_cam = xyz @ T.rotation.matrix().T + T.translation
    front = xyz_cam[:, 2] > 0
    xyz_cam = xyz_cam[front]
    uv = np.asarray(image.camera.img_from_cam(xyz_cam), dtype=np.float64).reshape(-1, 2)
    return uv, xyz_cam


def sparse_depth(rec: Any, image_id: int, radius_px: int = 0, min_track_length: int = 2) -> np.ndarray:
    """The (H, W) float32 SfM depth map of one registered image (SfM units, 0 = no point)."""
    cam = rec.images[image_id].camera
    uv, xyz_cam = frame_points(rec, image_id, min_track_length)
    return splat_depth(uv, xyz_cam[:, 2], cam.width, cam.height, radius_px)

"""The label update of the semantic TSDF: which voxels a frame's labels go to, found without per-sample hashing.

Both paths sample the same voxels (see :mod:`cadalign.fuse.tsdf`): every valid pixel casts ``n`` samples
along its ray, one voxel apart, inside ``+-label_band/2`` of its depth, i.e. ``|sdf| < trunc/2``.

- ``reference`` (the first implementation, kept as the benchmark baseline): the voxel index of every sample,
  then one Open3D hash-map query per sample (~400k a frame at 640x480) for its block.
- ``frustum`` (:mod:`cadalign.fuse.tsdf_frustum`): the samples' blocks are deduplicated with a mask over
  their bounding box (cells: :func:`block_cells`), the hash map is asked once per distinct block (~10-30k),
  and a dense table over the box gives every sample its buffer row with one array lookup. Per-camera ray slopes are
  computed once. The positions use the same float32 operations in the same order as the reference, so both
  paths write identical values (a test checks this bit for bit, across hash-map growth).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_TABLE_CELLS = 1 << 25
"""Largest box of blocks a frame may span for the frustum path (a bool mask and an int32 table of this many
cells, 160 MB); a frame seeing further falls back to the reference path."""


def block_cells(blocks: np.ndarray, lo: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """(M,) int64 cell of (3, M) int32 block keys in the box ``lo`` (3,), ``shape`` (3,) (x-major:
    ``(x * sy + y) * sz + z`` relative to ``lo``)."""
    sy, sz = int(shape[1]), int(shape[2])
    cells = (blocks[0] - np.int32(lo[0])).astype(np.int64) * (sy * sz)
    cells += (blocks[1] - np.int32(lo[1])) * np.int64(sz)
    cells += blocks[2] - np.int32(lo[2])
    return cells


def keys_of_cells(cells: np.ndarray, lo: np.ndarray, shape: np.ndarray) -> np.ndarray:
    """(K, 3) int32 block keys of (K,) int64 cells of the box (the inverse of :func:`block_cells`)."""
    sy, sz = int(shape[1]), int(shape[2])
    x, rest = np.divmod(cells, sy * sz)
    y, z = np.divmod(rest, sz)
    return np.stack([x + lo[0], y + lo[1], z + lo[2]], axis=1).astype(np.int32)


def band_pixels(mask: np.ndarray, stride: int, phase: int = 0) -> np.ndarray:
    """Flat indices of the valid pixels on a ``stride`` grid shifted by ``phase`` (0 .. stride^2 - 1: rows
    ``phase // stride``, ``+ stride``, ...; columns ``phase % stride``, ...)."""
    if stride == 1:
        return np.flatnonzero(mask)
    r, c = divmod(phase % (stride * stride), stride)
    sub = np.zeros_like(mask)
    sub[r::stride, c::stride] = mask[r::stride, c::stride]
    return np.flatnonzero(sub)


def label_stride(max_stride: int, voxel_m: float, fx: float, depth_m: np.ndarray) -> int:
    """The pixel stride of a frame's label samples: ``max_stride`` at most, and at most as large as keeps
    neighbouring samples within 2 voxels of each other at the frame's median depth (``depth_m`` (P,) of the
    valid pixels), so coarse pixels (far surfaces, small images) keep every pixel."""
    if max_stride <= 1 or len(depth_m) == 0:
        return 1
    pixel_m = float(np.median(depth_m)) / fx
    return int(max(1, min(max_stride, np.floor(2 * voxel_m / pixel_m))))


@dataclass(frozen=True)
class Rays:
    """Per-pixel ray slopes ``x = (u + 0.5 - cx) / fx``, ``y = (v + 0.5 - cy) / fy`` (float32) of one camera.

    The values are computed exactly as the reference path does (float64, then rounded to float32), once per
    camera instead of once per frame.
    """

    key: tuple[float, ...]
    x: np.ndarray
    y: np.ndarray

    @staticmethod
    def of_key(K: np.ndarray, width: int, height: int) -> tuple[float, ...]:
        """What the slopes depend on: fx, fy, cx, cy, width, height."""
        return (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), float(width), float(height))

    @staticmethod
    def of(K: np.ndarray, width: int, height: int) -> Rays:
        key = Rays.of_key(K, width, height)
        fx, fy, cx, cy = key[:4]
        v, u = np.divmod(np.arange(width * height, dtype=np.int64), width)
        x = ((u + np.float32(0.5 - cx)) * np.float32(1 / fx)).astype(np.float32)
        y = ((v + np.float32(0.5 - cy)) * np.float32(1 / fy)).astype(np.float32)
        return Rays(key, x, y)


def band_offsets(band_voxels: float, voxel_m: float, cell_voxels: int = 1) -> np.ndarray:
    """Depth offsets (n,) float64 of the samples across the band, one label cell (``cell_voxels`` voxels)
    apart or closer, metres."""
    n = max(1, int(np.ceil(band_voxels / cell_voxels - 1e-6)))
    return ((np.arange(n) + 0.5) / n - 0.5) * (band_voxels * voxel_m)


def sample_voxels(x: np.ndarray, y: np.ndarray, z: np.ndarray, local_from_cam_vox: np.ndarray,
                  offsets: np.ndarray, cell_voxels: int = 1) -> np.ndarray:
    """(3, n P) int32 voxel indices of the samples (offset-major) of P pixels with ray slopes x, y and depth z.

    ``local_from_cam_vox`` is the 4x4 local-from-camera transform with the translation in voxels and the
    rotation divided by the voxel size (float32 arithmetic in the reference path's order). With
    ``cell_voxels`` > 1 each index is that of its label cell's holder voxel (see :func:`cell_holder`).
    """
    R = local_from_cam_vox[:3, :3].astype(np.float32)
    t = local_from_cam_vox[:3, 3].astype(np.float32)
    p = len(z)
    out = np.empty((3, len(offsets) * p), dtype=np.int32)
    tmp = np.empty(p, dtype=np.float32)
    zo = np.empty(p, dtype=np.float32)
    for k in range(3):
        d = x * R[k, 0]
        d += y * R[k, 1]
        d += R[k, 2]
        for j, o in enumerate(offsets):
            np.add(z, np.float32(o), out=zo)
            np.multiply(zo, d, out=tmp)
            tmp += t[k]
            np.rint(tmp, out=tmp)
            out[k, j * p:(j + 1) * p] = tmp
    return cell_holder(out, cell_voxels)


def cell_holder(vox: np.ndarray, cell_voxels: int) -> np.ndarray:
    """In place: int32 voxel indices -> the lowest-index voxel of their label cell (``cell_voxels`` a power of
    two: clear the low bits, a floor division that also holds for negative indices)."""
    if cell_voxels > 1:
        np.bitwise_and(vox, np.int32(-cell_voxels), out=vox)
    return vox


def split_blocks(vox: np.ndarray, res: int) -> tuple[np.ndarray, np.ndarray]:
    """(3, M) int32 block keys and (M,) int32 offsets ``x + res * (y + res * z)`` inside the block of (3, M)
    int32 voxel indices (floor division: negative indices belong to negative blocks)."""
    shift = res.bit_length() - 1
    if (1 << shift) == res:  # arithmetic shift and mask: the floor division and remainder of a power of two
        block = vox >> shift
        loc = vox & np.int32(res - 1)
    else:
        block = np.floor_divide(vox, res)
        loc = vox - block * np.int32(res)
    local = loc[0]
    local += loc[1] * np.int32(res)
    local += loc[2] * np.int32(res * res)
    return block, local

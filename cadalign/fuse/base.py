"""What every semantic map consumes and produces: one frame in, labelled geometry out.

Both maps (:class:`~cadalign.fuse.tsdf.SemanticTSDF`, :class:`~cadalign.fuse.surfel.SurfelMap`) follow
:class:`SemanticMap`: ``integrate(frame)`` then ``extract_mesh()`` / ``extract_points()``. Maps work in a
local frame ``local = world - origin`` (float64 origin chosen from the first frame) so that world coordinates
far from zero (UTM) keep millimetre precision in the float32 map; outputs are in world coordinates again.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from cadalign.errors import InputError
from cadalign.types import Camera, Rigid3


@dataclass(frozen=True)
class FuseFrame:
    """One posed RGB-D frame with per-pixel class probabilities.

    Attributes:
        depth_m: (H, W) z-depth in metres; 0 or non-finite = invalid.
        probs: (C, H, W) class probabilities (need not be exactly normalised; they are clamped on use).
        camera: pinhole intrinsics (pixel centres at integer + 0.5, see :mod:`cadalign.types`).
        T_cam_from_world: the camera pose.
        rgb: (H, W, 3) uint8 colour, or None (grey).
    """

    depth_m: np.ndarray
    probs: np.ndarray
    camera: Camera
    T_cam_from_world: Rigid3
    rgb: np.ndarray | None = None

    def __post_init__(self) -> None:
        h, w = self.camera.height, self.camera.width
        if np.shape(self.depth_m) != (h, w):
            raise InputError(f"depth map has shape {np.shape(self.depth_m)}; the camera is {w}x{h} "
                             f"(expected ({h}, {w}))")
        if np.ndim(self.probs) != 3 or np.shape(self.probs)[1:] != (h, w):
            raise InputError(f"class probabilities must be (C, {h}, {w}); got {np.shape(self.probs)}")
        if self.rgb is not None and np.shape(self.rgb) != (h, w, 3):
            raise InputError(f"rgb must be ({h}, {w}, 3) uint8; got {np.shape(self.rgb)}")


@dataclass(frozen=True)
class LabelledGeometry:
    """A labelled point set or mesh in world coordinates.

    Attributes:
        points_m: (N, 3) float64 world positions, metres.
        normals: (N, 3) float32 unit normals.
        colors: (N, 3) uint8 RGB.
        labels: (N,) int64 class with the highest fused probability.
        probs: (N, C) float32 fused class probabilities (rows sum to 1).
        faces: (F, 3) int64 triangle indices for a mesh, None for a point cloud.
    """

    points_m: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    labels: np.ndarray
    probs: np.ndarray
    faces: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.points_m)


class SemanticMap(Protocol):
    """The interface both maps implement (see the module docstring)."""

    n_classes: int
    origin: np.ndarray
    frames_integrated: int

    def integrate(self, frame: FuseFrame) -> None: ...

    def extract_mesh(self) -> LabelledGeometry: ...

    def extract_points(self) -> LabelledGeometry: ...


def valid_depth(depth_m: np.ndarray, depth_min_m: float, depth_max_m: float) -> np.ndarray:
    """(H, W) bool: finite depth inside ``[depth_min_m, depth_max_m]``."""
    d = np.asarray(depth_m)
    with np.errstate(invalid="ignore"):
        return np.isfinite(d) & (d >= depth_min_m) & (d <= depth_max_m)


def require_valid_depth(frame: FuseFrame, depth_min_m: float, depth_max_m: float, name: str = "frame",
                        n_classes: int | None = None) -> np.ndarray:
    """The valid-depth mask of a frame; raises if no pixel has usable depth (or the class count is wrong)."""
    if n_classes is not None and np.shape(frame.probs)[0] != n_classes:
        raise InputError(f"{name} has probabilities for {np.shape(frame.probs)[0]} classes, the map {n_classes}; "
                         "fuse frames of the same class list into one map")
    mask = valid_depth(frame.depth_m, depth_min_m, depth_max_m)
    if not mask.any():
        d = np.asarray(frame.depth_m)
        fin = d[np.isfinite(d) & (d > 0)]
        seen = f"valid depths span [{fin.min():.3g}, {fin.max():.3g}] m" if fin.size else "no positive finite depth"
        raise InputError(f"{name} has no valid depth in [{depth_min_m}, {depth_max_m}] m ({seen}); check the depth "
                         "source and units (metres), or raise depth_max_m")
    return mask


def origin_from_frame(frame: FuseFrame, mask: np.ndarray, block_m: float) -> np.ndarray:
    """A local map origin: the median of the frame's back-projected points, snapped to the block grid."""
    v, u = np.nonzero(mask)
    z = np.asarray(frame.depth_m, dtype=np.float64)[v, u]
    cam = frame.camera
    x = (u + 0.5 - cam.cx) / cam.fx * z
    y = (v + 0.5 - cam.cy) / cam.fy * z
    world = frame.T_cam_from_world.inverse().apply(np.stack([x, y, z], axis=1))
    return np.round(np.median(world, axis=0) / block_m) * block_m


def probs_from_stored(stored: np.ndarray) -> np.ndarray:
    """(N, C) stored relative log-probabilities -> normalised float32 probabilities (a softmax)."""
    s = stored.astype(np.float64)
    p = np.exp(s - s.max(axis=1, keepdims=True))
    return (p / p.sum(axis=1, keepdims=True)).astype(np.float32)

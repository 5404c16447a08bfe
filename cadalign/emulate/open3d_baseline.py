"""Open3D ray casting alone: the baseline the emulation benches divide their time by.

What a user who skips cadalign would write: one ``o3d.t.geometry.RaycastingScene`` over the mesh and one
``cast_rays`` call on the sensor's rays, keeping the hit points. No ray-pattern cache, range window, noise or
colour/class lookup, which :func:`cadalign.emulate.lidar.scan` adds on top of the same cast.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class Open3DRaycast:
    """A ``RaycastingScene`` over ``vertices (V, 3)`` / ``faces (F, 3)`` in world metres."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        import open3d as o3d  # lazy: heavy dependency (open3d)

        self._scene: Any = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                                  o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)))

    def hit_points(self, origin: np.ndarray, unit_dirs: np.ndarray) -> np.ndarray:
        """World points ``(M, 3)`` where the rays from ``origin (3,)`` along ``unit_dirs (N, 3)`` hit, in ray order."""
        import open3d as o3d  # lazy: heavy dependency (open3d)

        rays = np.empty((len(unit_dirs), 6), np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = unit_dirs
        t = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy()
        hit = np.isfinite(t)
        return rays[hit, :3].astype(np.float64) + rays[hit, 3:].astype(np.float64) * t[hit, None]

"""Photo -> mesh -> LiDAR scan against the same scan of the CAD scene (issue 47's error against exact truth).

The same rays (a LiDAR pattern from one pose) are cast into the layered mesh of a photo (moved to the world
by the photo's true camera pose) and into the CAD scene. A ray counts when its CAD hit is a surface *seen
in the photo*: the hit projects inside the image and its depth matches the photo's true depth at that
pixel within ``seen_rel`` (not occluded from the camera). Reported over those rays: how many the photo's
mesh also hits (coverage), the absolute range error (median, 90th percentile) and the share whose class
agrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cadalign.emulate import lidar
from cadalign.emulate.mesh import LayeredMesh
from cadalign.emulate.raycast_engines import make_engine
from cadalign.geometry import project
from cadalign.types import Camera, Rigid3


@dataclass(frozen=True)
class ScanAgreement:
    """Agreement of a photo mesh's scan with the CAD scan over rays that hit surfaces seen in the photo.

    Attributes:
        n_seen: rays whose CAD hit is seen in the photo.
        coverage: share of those the photo mesh also hits.
        range_err_median_m: median |range(photo mesh) - range(CAD)| over rays hit by both, metres.
        range_err_p90_m: its 90th percentile, metres.
        rel_range_err_median: median of that error over the CAD range.
        class_agreement: share of rays hit by both whose class ids agree.
    """

    n_seen: int
    coverage: float
    range_err_median_m: float
    range_err_p90_m: float
    rel_range_err_median: float
    class_agreement: float


def seen_in_photo(xyz_world: np.ndarray, camera: Camera, T_world_from_cam: Rigid3, depth_m: np.ndarray,
                  seen_rel: float = 0.02) -> np.ndarray:
    """(N,) bool: each world point projects into the photo and lies at its true depth (within ``seen_rel``)."""
    X = T_world_from_cam.inverse().apply(np.asarray(xyz_world, np.float64))
    uv, front = project(camera.K, X)
    uv = np.where(front[:, None], uv, -1.0)  # NaN rows would warn in the integer cast
    col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    inside = front & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    ok = np.zeros(len(X), bool)
    d = depth_m[row[inside], col[inside]]
    ok[inside] = (d > 0) & (np.abs(X[inside, 2] - d) <= seen_rel * np.maximum(d, 1e-9))
    return ok


def compare_with_cad(photo_mesh_world: LayeredMesh, cad_mesh: LayeredMesh, T_world_from_sensor: Rigid3,
                     cfg: lidar.LidarConfig, camera: Camera, T_world_from_cam: Rigid3, true_depth_m: np.ndarray,
                     seen_rel: float = 0.02) -> ScanAgreement:
    """Cast ``cfg``'s rays from ``T_world_from_sensor`` into both meshes and compare (see the module docstring).

    ``true_depth_m`` is the photo's exact z-depth (H, W), used only to decide which CAD hits the photo sees.
    """
    d, _, _, _ = lidar.scan_directions(cfg)
    d_world = d @ T_world_from_sensor.R.T
    a = make_engine(cfg.engine, photo_mesh_world.vertices_m, photo_mesh_world.faces).cast_unit(
        T_world_from_sensor.t, d_world)
    b = make_engine(cfg.engine, cad_mesh.vertices_m, cad_mesh.faces).cast_unit(T_world_from_sensor.t, d_world)
    hit_b = b.hit & (b.range_m <= cfg.max_range_m)
    xyz_b = T_world_from_sensor.t + d_world[hit_b] * b.range_m[hit_b, None]
    seen = np.zeros(len(d), bool)
    seen[hit_b] = seen_in_photo(xyz_b, camera, T_world_from_cam, true_depth_m, seen_rel)
    both = seen & a.hit
    n_seen, n_both = int(seen.sum()), int(both.sum())
    if n_both == 0:
        return ScanAgreement(n_seen, 0.0, float("nan"), float("nan"), float("nan"), float("nan"))
    err = np.abs(a.range_m[both] - b.range_m[both])
    cls_a = photo_mesh_world.class_id[a.face[both]]
    cls_b = cad_mesh.class_id[b.face[both]]
    return ScanAgreement(n_seen, n_both / n_seen, float(np.median(err)), float(np.percentile(err, 90)),
                         float(np.median(err / b.range_m[both])), float(np.mean(cls_a == cls_b)))

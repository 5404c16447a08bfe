"""Novel views of a layered mesh, CAD scene or fused map: RGB, depth, class, part and pane images.

One ray per pixel centre ``K^-1 (u + 0.5, v + 0.5, 1)`` (:func:`cadalign.geometry.pixel_rays`) from an
OpenCV camera (x right, y down, z forward) at ``T_world_from_cam``. Colour is the mesh's vertex colour
interpolated with the hit's barycentrics when the mesh has vertex colours (so a layered mesh seen from its
own camera reproduces its image), else the face colour; no lighting is applied.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from cadalign.config import bounded
from cadalign.emulate.mesh import LayeredMesh
from cadalign.emulate.raycast_engines import BVHEngine, TorchEngine, make_engine
from cadalign.geometry import pixel_rays
from cadalign.types import Camera, Rigid3


@dataclass(frozen=True)
class ViewConfig:
    width: int = bounded(640, ge=1)
    """Image width, pixels."""
    height: int = bounded(480, ge=1)
    """Image height, pixels."""
    hfov_deg: float = bounded(70.0, gt=0.0, lt=180.0)
    """Horizontal field of view, degrees (square pixels, principal point at the centre)."""
    max_range_m: float = bounded(1000.0, gt=0.0)
    """Surfaces farther than this are not seen, metres."""
    engine: Literal["bvh", "torch"] = "bvh"
    """Ray caster."""
    device: str = "cpu"
    """Torch engine device."""

    def camera(self) -> Camera:
        f = 0.5 * self.width / np.tan(np.radians(self.hfov_deg) / 2)
        return Camera(np.array([[f, 0, self.width / 2], [0, f, self.height / 2], [0, 0, 1.0]]), self.width,
                      self.height)


PRESETS: dict[str, ViewConfig] = {
    "default": ViewConfig(),
    "small": ViewConfig(width=160, height=120),
    "hd": ViewConfig(width=1280, height=720, hfov_deg=80.0),
}


@dataclass(frozen=True)
class ViewFrame:
    """One rendered view (H x W).

    Attributes:
        rgb: (H, W, 3) uint8; black where nothing is hit.
        depth_m: (H, W) float32 z-depth, 0 where nothing is hit.
        range_m: (H, W) float32 distance along the ray, inf where nothing is hit.
        class_id: (H, W) int32 (0 where nothing is hit).
        part_id: (H, W) int32 (0 where nothing is hit).
        pane_id: (H, W) int32 (0 where nothing is hit).
        face: (H, W) int64 face index, -1 where nothing is hit.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    range_m: np.ndarray
    class_id: np.ndarray
    part_id: np.ndarray
    pane_id: np.ndarray
    face: np.ndarray


def render(mesh: LayeredMesh, camera: Camera, T_world_from_cam: Rigid3, *, max_range_m: float = np.inf,
           engine: BVHEngine | TorchEngine | None = None, engine_name: str = "bvh",
           device: str = "cpu") -> ViewFrame:
    """Render ``mesh`` from ``T_world_from_cam`` with pinhole ``camera`` (see the module docstring).

    Pass a built ``engine`` to reuse it over many views; otherwise one called ``engine_name`` is built.
    """
    engine = engine or make_engine(engine_name, mesh.vertices_m, mesh.faces, device=device)  # type: ignore[arg-type]
    H, W = camera.height, camera.width
    rays = pixel_rays(camera.K, W, H).reshape(-1, 3)
    norm = np.linalg.norm(rays, axis=1)
    hits = engine.cast_unit(T_world_from_cam.t, (rays / norm[:, None]) @ T_world_from_cam.R.T)
    hit = hits.hit & (hits.range_m <= max_range_m)
    face = np.where(hit, hits.face, -1)
    f = np.maximum(face, 0)

    def layer(values: np.ndarray) -> np.ndarray:
        return np.where(hit, values[f], 0).astype(np.int32).reshape(H, W)

    depth = np.where(hit, hits.range_m / norm, 0.0).astype(np.float32)
    rng = np.where(hit, hits.range_m, np.inf).astype(np.float32)
    return ViewFrame(mesh.hit_rgb(face, hits.bary).reshape(H, W, 3), depth.reshape(H, W), rng.reshape(H, W),
                     layer(mesh.class_id), layer(mesh.part_id), layer(mesh.pane_id), face.reshape(H, W))

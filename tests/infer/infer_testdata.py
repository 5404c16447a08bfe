"""Close-up exact renders of one CAD model for refinement tests (ray cast: exact mask and depth)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cadalign.cad.model import CadModel
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.raycast.core import RaycastRenderer, RenderMesh
from cadalign.types import Camera, Rigid3


@dataclass(frozen=True)
class CloseView:
    camera: Camera
    T_cam_from_obj: Rigid3
    mask: np.ndarray
    depth_m: np.ndarray


def look_at(eye: np.ndarray, target: np.ndarray, up: tuple[float, float, float] = (0.0, 0.0, 1.0)) -> Rigid3:
    """``T_world_from_cam`` of a camera at ``eye`` looking at ``target`` (x right, y down, z forward)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return Rigid3(np.stack([x, y, z], axis=1), eye)


def render_close_view(model: CadModel, eye: np.ndarray, size: tuple[int, int] = (160, 120),
                      f: float = 150.0) -> CloseView:
    """The model (world = model frame) seen from ``eye`` looking at its bounding-box centre."""
    w, h = size
    cam = Camera(np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]]), w, h)
    centre = (model.bbox_min + model.bbox_max) / 2
    T_wc = look_at(np.asarray(eye, float), centre)
    r = RaycastRenderer([RenderMesh(model.vertices_m, model.faces, 1, 1)], cam).render(T_wc)
    return CloseView(cam, T_wc.inverse(), r.instance == 1, r.depth_m)


def perturb(T: Rigid3, t_m: float, r_deg: float, seed: int) -> Rigid3:
    """``T`` with its rotation turned by exactly ``r_deg`` and its translation moved by exactly ``t_m``."""
    rng = np.random.default_rng(seed)
    a, d = rng.normal(size=3), rng.normal(size=3)
    dR = axis_angle_to_matrix(a / np.linalg.norm(a) * np.radians(r_deg))
    return Rigid3(dR @ T.R, T.t + t_m * d / np.linalg.norm(d))

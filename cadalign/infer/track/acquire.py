"""Wide-basin start from a rough pose: a search of the camera's pan, tilt and roll against the image's edges.

A navigation pose (USBL/DVL, ~0.5 m / 10 deg) puts the structure tens of pixels from where the image shows it,
beyond the reach of the contour fit (:mod:`cadalign.infer.track.edges`). Most of such an error is the camera's
orientation, which moves the whole view: so the CAD's occluding contours at the rough pose are drawn into a
template at a low resolution, turned through a range of rolls, and correlated with the image's edge strength
over all shifts (``cv2.matchTemplate``). The best few (shift, roll) peaks become camera rotations, each is
refined by the contour fit, and the caller keeps the best-supported result.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cadalign.align.edge_refine import EdgeRefineConfig, contour_samples
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.track.edges import EdgeTracker
from cadalign.types import Rigid3


@dataclass(frozen=True)
class AcquireConfig:
    """The pan/tilt/roll search of a rough pose."""

    scale: float = 0.25
    """Image scale of the search (one of the tracker's level scales)."""
    max_turn_deg: float = 15.0
    """Largest pan/tilt searched, degrees (a navigation pose is good to about 10 deg)."""
    max_roll_deg: float = 10.0
    """Largest roll searched, degrees."""
    roll_step_deg: float = 2.5
    """Roll step, degrees."""
    candidates: int = 4
    """Peaks refined by the contour fit."""
    blur_px: float = 1.0
    """Gaussian sigma of the edge-strength image, pixels of the search scale (tolerance to the pose's
    remaining error)."""


def _edge_strength(gray: np.ndarray, blur_px: float) -> np.ndarray:
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    m = np.sqrt(gx * gx + gy * gy)
    if m.ndim == 3:  # colour: the strongest channel's gradient
        m = m.max(axis=2)
    m = m / max(float(np.percentile(m, 99)), 1e-6)  # contrast-free: turbid and clear water alike
    m = np.minimum(m, 1.0)
    return cv2.GaussianBlur(m, (0, 0), blur_px) if blur_px > 0 else m


def candidates(tracker: EdgeTracker, gray: np.ndarray, T_world_from_cam: Rigid3,
               cfg: AcquireConfig | None = None) -> list[tuple[float, Rigid3]]:
    """(score, ``T_world_from_cam``) of the best (pan, tilt, roll) turns of the camera at a rough pose, best
    first; empty when the CAD shows no contour there. ``gray``: the full-resolution frame (float32 0-255)."""

    cfg = cfg or AcquireConfig()
    r = tracker.renderer(tracker.usable(cfg.scale))
    cam = r.camera
    f = r.render(T_world_from_cam, with_full_masks=False, with_normals=False)
    X_cam, _, _ = contour_samples(f.depth_m, f.rays_cam, f.range_m, EdgeRefineConfig(point_step=1), f.instance)
    if len(X_cam) < 10:
        return []
    g = cv2.resize(gray, (cam.width, cam.height), interpolation=cv2.INTER_AREA)
    E = _edge_strength(g, cfg.blur_px)
    S = int(np.ceil(cam.fx * np.tan(np.radians(cfg.max_turn_deg))))
    Ep = cv2.copyMakeBorder(E, S, S, S, S, cv2.BORDER_CONSTANT, value=0.0)
    rolls = np.arange(-cfg.max_roll_deg, cfg.max_roll_deg + 1e-9, cfg.roll_step_deg)
    maps = []
    for roll in rolls:
        Xr = X_cam @ axis_angle_to_matrix(np.array([0.0, 0.0, np.radians(roll)])).T
        p = Xr @ cam.K.T
        uv = np.floor(p[:, :2] / p[:, 2:3]).astype(int)  # pixel index (centres at +0.5 in K)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        tpl = np.zeros((cam.height, cam.width), np.float32)
        tpl[uv[ok, 1], uv[ok, 0]] = 1.0
        n = max(float(tpl.sum()), 1.0)
        maps.append(cv2.matchTemplate(Ep, tpl, cv2.TM_CCORR) / n)  # (2S+1, 2S+1): mean edge strength
    M = np.stack(maps)  # (rolls, dy, dx)
    out: list[tuple[float, Rigid3]] = []
    work = M.copy()
    sup = max(2, S // 6)  # peaks closer than this (pixels) or one roll step are one peak
    for _ in range(cfg.candidates):
        k, iy, ix = np.unravel_index(int(np.argmax(work)), work.shape)
        score = float(work[k, iy, ix])
        if not np.isfinite(score) or score <= 0:
            break
        dx, dy = ix - S, iy - S  # the image shows the contours shifted by (dx, dy) from the rough pose
        # a camera turn that shifts the view by (dx, dy): pan about y (+x shift), tilt about x (-y shift)
        R = (axis_angle_to_matrix(np.array([0.0, np.arctan2(dx, cam.fx), 0.0]))
             @ axis_angle_to_matrix(np.array([-np.arctan2(dy, cam.fy), 0.0, 0.0]))
             @ axis_angle_to_matrix(np.array([0.0, 0.0, np.radians(rolls[k])])))
        T_cw = Rigid3(R, np.zeros(3)) @ T_world_from_cam.inverse()
        out.append((score, T_cw.inverse()))
        work[max(k - 1, 0):k + 2, max(iy - sup, 0):iy + sup + 1, max(ix - sup, 0):ix + sup + 1] = -np.inf
    return out

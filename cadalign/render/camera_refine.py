"""Per-frame camera refinement against the aligned CAD, and a per-frame validity check.

SfM cameras carry the SfM's own error (about 0.4 % of the scene distance on murky video), which is several
centimetres at 8 m: more than the CAD ground truth should inherit. After the alignment, each frame's SfM
observations whose 3D point lies on the CAD are snapped to the CAD surface (the exact geometry), and the
camera pose is re-estimated from those 2D-3D pairs by robust iterative PnP (Levenberg-Marquardt from the
SfM pose, inliers by reprojection error). A frame with too few such pairs, or whose refined pose jumps far
from the SfM pose (a frame of a folded or drifted part of the model), is reported as not verified.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from cadalign.geometry import geodesic_angle
from cadalign.types import Rigid3, Sim3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraRefineConfig:
    snap_max_m: float = 0.03
    """SfM points farther than this from the CAD surface (after alignment) are not used, metres."""
    inlier_px: float = 2.0
    """Final reprojection-error threshold for PnP inliers, pixels."""
    min_inliers: int = 15
    """Fewer inliers than this: keep the SfM pose and mark the frame not verified."""
    max_shift_m: float = 0.25
    """A refined centre farther than this from the SfM one marks the frame not verified, metres."""
    max_turn_deg: float = 2.0
    """A refined orientation turned more than this from the SfM one marks the frame not verified."""


@dataclass(frozen=True)
class RefinedCamera:
    T_world_from_cam: Rigid3
    verified: bool
    n_pairs: int
    n_inliers: int
    rms_px: float
    shift_m: float
    turn_deg: float


def refine_cameras(rec: Any, cad_from_sfm: Sim3, vertices_m: np.ndarray, faces: np.ndarray,
                   cfg: CameraRefineConfig) -> dict[str, RefinedCamera]:
    """Refine every registered camera of ``rec`` (a ``pycolmap.Reconstruction``) against the CAD mesh (world, m)."""
    import open3d as o3d

    from cadalign.render.raycast import _o3d_mesh

    origin = vertices_m.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(_o3d_mesh(vertices_m - origin, faces))
    out = {}
    for im in rec.images.values():
        if not im.has_pose:
            continue
        obs = [(p.xy, rec.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
        uv = np.array([o[0] for o in obs], dtype=np.float64).reshape(-1, 2)
        X = cad_from_sfm.apply(np.array([o[1] for o in obs], dtype=np.float64).reshape(-1, 3))
        closest = scene.compute_closest_points(o3d.core.Tensor((X - origin).astype(np.float32)))
        snapped = closest["points"].numpy().astype(np.float64) + origin
        near = np.linalg.norm(snapped - X, axis=1) < cfg.snap_max_m
        T_sfm = rec.images[im.image_id].cam_from_world()
        R_cw, t_cw = T_sfm.rotation.matrix(), np.asarray(T_sfm.translation)
        T0 = Rigid3(cad_from_sfm.R @ R_cw.T, cad_from_sfm.apply((-R_cw.T @ t_cw)[None])[0])
        # normalised, undistorted image coordinates through the SfM camera model (any COLMAP model);
        # PnP then runs with K = I and pixel thresholds scaled by the focal length
        xy = np.asarray(im.camera.cam_from_img(uv), dtype=np.float64).reshape(-1, 2) if len(uv) else uv
        out[im.name] = _refine_one(xy[near], snapped[near], float(im.camera.mean_focal_length()), T0, cfg)
    return out


def rays_of(cam) -> np.ndarray:  # noqa: ANN001  (a pycolmap.Camera)
    """(H, W, 3) rays with z = 1 through the pixel centres (COLMAP: first pixel centre at 0.5) of ``cam``."""
    w, h = int(cam.width), int(cam.height)
    uu, vv = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xy = np.asarray(cam.cam_from_img(np.stack([uu.ravel(), vv.ravel()], 1)), dtype=np.float64)
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1).reshape(h, w, 3)


def _refine_one(xy: np.ndarray, X: np.ndarray, focal_px: float, T0: Rigid3, cfg: CameraRefineConfig) -> RefinedCamera:
    import cv2

    n = len(xy)
    if n < cfg.min_inliers:
        return RefinedCamera(T0, False, n, 0, float("nan"), 0.0, 0.0)
    uv, K_cv = xy * focal_px, np.diag([focal_px, focal_px, 1.0])  # an ideal pinhole in "pixels"
    T_cw = T0.inverse()
    rvec, tvec = cv2.Rodrigues(T_cw.R)[0], T_cw.t.reshape(3, 1).copy()
    keep = np.ones(n, dtype=bool)
    for thr in (8.0, 4.0, cfg.inlier_px):
        err = _reproj(X, uv, K_cv, rvec, tvec)
        keep = err < thr
        if keep.sum() < cfg.min_inliers:
            return RefinedCamera(T0, False, n, int(keep.sum()), float("nan"), 0.0, 0.0)
        rvec, tvec = cv2.solvePnPRefineLM(X[keep], uv[keep], K_cv, None, rvec, tvec)
    err = _reproj(X, uv, K_cv, rvec, tvec)
    keep = err < cfg.inlier_px
    R = cv2.Rodrigues(rvec)[0]
    T = Rigid3(R, tvec.ravel()).inverse()
    shift = float(np.linalg.norm(T.t - T0.t))
    turn = float(np.degrees(geodesic_angle(T.R, T0.R)))
    ok = keep.sum() >= cfg.min_inliers and shift <= cfg.max_shift_m and turn <= cfg.max_turn_deg
    rms = float(np.sqrt(np.mean(err[keep] ** 2))) if keep.any() else float("nan")
    return RefinedCamera(T if ok else T0, bool(ok), n, int(keep.sum()), rms, shift, turn)


def _reproj(X: np.ndarray, uv: np.ndarray, K: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    import cv2

    proj, _ = cv2.projectPoints(X, rvec, tvec, K, None)
    return np.linalg.norm(proj.reshape(-1, 2) - uv, axis=1)

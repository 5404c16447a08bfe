"""Camera refinement against the aligned CAD (a CAD-anchored bundle adjustment) and a per-frame check.

SfM cameras carry the SfM's own error: a self-calibrated focal length off by ~1 % (it trades against the
camera distance) and ~0.4 % of the scene distance in position on murky video, i.e. several centimetres
and pixels at 8 m, more than the CAD ground truth should inherit. After the alignment, every SfM point
that lies on the CAD is moved onto the CAD surface (the exact, metric geometry) and held fixed; a bundle
adjustment then re-estimates all camera poses and the shared focal length and distortion from the
frames' observations of those anchored points (robust Cauchy loss, two rounds with outlier removal).
With the points fixed there is no gauge freedom and no scale drift: the intrinsics are calibrated by
the CAD itself.

Each frame is then checked: enough observations that reproject within ``inlier_px``, and a refined pose
that did not jump from the SfM pose (a frame of a folded or drifted part of the model has few points on
the CAD and moves far); a frame failing the check is "not verified" and keeps its SfM pose.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np

from cadalign.align.edge_refine import EdgeRefineConfig
from cadalign.geometry import geodesic_angle
from cadalign.raycast.core import MeshQuery
from cadalign.sfm.colmap_log import stderr_captured
from cadalign.types import Rigid3, Sim3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraRefineConfig:
    snap_max_m: float = 0.03
    """SfM points farther than this from the CAD surface (after alignment) are not used, metres."""
    intrinsics: bool = True
    """Refine the shared focal length and distortion against the CAD (off: only the poses move; use it
    when the camera was calibrated and the calibration was given to SfM)."""
    loss_px: float = 1.0
    """Cauchy loss scale of the anchored bundle adjustment, pixels."""
    rounds: int = 2
    """Bundle adjustment rounds; observations above ``4 * inlier_px`` are dropped between rounds."""
    max_iterations: int = 100
    """Solver iterations per round."""
    inlier_px: float = 2.0
    """Reprojection error below which an observation counts as an inlier of its frame, pixels."""
    min_inliers: int = 15
    """Fewer inliers than this: keep the SfM pose and mark the frame not verified."""
    max_shift_m: float = 0.25
    """A refined centre farther than this from the SfM one marks the frame not verified, metres."""
    max_turn_deg: float = 2.0
    """A refined orientation turned more than this from the SfM one marks the frame not verified."""
    edges: EdgeRefineConfig = EdgeRefineConfig()
    """Then align the verified frames to the CAD's contours in the images
    (:mod:`cadalign.align.edge_refine`): what the anchored adjustment leaves (the rig sliding along planar
    faces, each frame's own error) is about half a pixel at 10 m."""


@dataclass(frozen=True)
class RefinedCamera:
    T_world_from_cam: Rigid3
    verified: bool
    n_pairs: int
    n_inliers: int
    rms_px: float
    shift_m: float
    turn_deg: float


@dataclass(frozen=True)
class CameraRefineResult:
    """Per-frame cameras (metres, CAD world frame), the anchored model (SfM units) and a summary.

    ``model`` is a ``pycolmap.Reconstruction`` whose cameras carry the refined intrinsics: render with
    its cameras (:func:`rays_of`), not the SfM ones. Poses of frames that are not verified are the SfM
    poses in ``frames`` (the model holds whatever the adjustment made of them).
    """

    frames: dict[str, RefinedCamera]
    model: Any
    summary: dict[str, Any]


def _world_pose(T_cam_from_world_sfm: Any, cad_from_sfm: Sim3) -> Rigid3:
    R_cw, t_cw = T_cam_from_world_sfm.rotation.matrix(), np.asarray(T_cam_from_world_sfm.translation)
    return cad_from_sfm.carry_pose(Rigid3(R_cw, t_cw).inverse())


def refine_cameras(rec: Any, cad_from_sfm: Sim3, vertices_m: np.ndarray, faces: np.ndarray,
                   cfg: CameraRefineConfig) -> CameraRefineResult:
    """Refine the registered cameras of ``rec`` (a ``pycolmap.Reconstruction``, left unchanged) against the
    CAD mesh (world frame, metres); see the module doc."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    model = pycolmap.Reconstruction(rec)
    ids = list(model.points3D)
    xyz = np.array([model.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    X = cad_from_sfm.apply(xyz)
    snapped = MeshQuery(vertices_m, faces).closest_points(X)
    near = np.linalg.norm(snapped - X, axis=1) < cfg.snap_max_m
    sfm_from_cad = cad_from_sfm.inverse()
    anchored = sfm_from_cad.apply(snapped)
    for k, pid in enumerate(ids):
        if near[k]:
            model.points3D[pid].xyz = anchored[k]
        else:
            model.delete_point3D(pid)
    cam_before = {cid: np.array(c.params) for cid, c in model.cameras.items()}
    model.update_point_3d_errors()  # the stored errors belong to the unsnapped points
    err_before = model.compute_mean_reprojection_error()
    for r in range(cfg.rounds):
        if r > 0:
            _drop_outliers(model, 4.0 * cfg.inlier_px)
        opts = pycolmap.BundleAdjustmentOptions()
        opts.print_summary = False
        opts.refine_points3D = False
        opts.refine_focal_length = cfg.intrinsics
        opts.refine_extra_params = cfg.intrinsics
        opts.refine_principal_point = False
        opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        opts.ceres.loss_function_scale = cfg.loss_px
        opts.ceres.solver_options.max_num_iterations = cfg.max_iterations
        opts.ceres.use_gpu = False
        _anchored_bundle_adjustment(model, opts)
    model.update_point_3d_errors()
    frames = {}
    for im in model.images.values():
        if not im.has_pose:
            continue
        frames[im.name] = _check(im, model, _world_pose(rec.images[im.image_id].cam_from_world(), cad_from_sfm),
                                 cad_from_sfm, cfg)
    summary = {
        "points_on_cad": int(near.sum()), "points": len(ids),
        "reprojection_px": {"before": err_before, "after": model.compute_mean_reprojection_error()},
        "cameras": {str(cid): {"model": c.model.name, "params_before": cam_before[cid].tolist(),
                               "params_after": list(map(float, c.params))} for cid, c in model.cameras.items()},
        "frames_verified": int(sum(f.verified for f in frames.values())), "frames": len(frames),
    }
    log.info("CAD-anchored refinement: %d of %d SfM points on the CAD, reprojection %.3f -> %.3f px, "
             "%d of %d frames verified", summary["points_on_cad"], summary["points"], err_before,
             summary["reprojection_px"]["after"], summary["frames_verified"], summary["frames"])
    return CameraRefineResult(frames, model, summary)


def _anchored_bundle_adjustment(model: Any, opts: Any) -> None:
    """Bundle adjustment with every 3D point held constant and *no* gauge fixing: the CAD-anchored
    points fix position, orientation and scale, so every camera (pycolmap's default would hold two
    cameras or three points fixed) is free to move."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    config = pycolmap.BundleAdjustmentConfig()
    for im in model.images.values():
        if im.has_pose:
            config.add_image(im.image_id)
    for pid in model.points3D:
        config.add_constant_point(pid)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.UNSPECIFIED)
    if config.num_residuals(model) == 0:
        return

    with stderr_captured():  # the adjuster logs at INFO whatever glog's flags say
        pycolmap.create_default_bundle_adjuster(opts, config, model).solve()


def _drop_outliers(model: Any, max_px: float) -> None:
    for im in model.images.values():
        if not im.has_pose:
            continue
        T = im.cam_from_world()
        for idx, p in enumerate(im.points2D):
            if not p.has_point3D():
                continue
            Xc = T * model.points3D[p.point3D_id].xyz
            if Xc[2] <= 0 or np.linalg.norm(im.camera.img_from_cam(Xc) - p.xy) > max_px:
                pid = p.point3D_id
                if model.points3D[pid].track.length() <= 1:
                    model.delete_point3D(pid)
                else:
                    model.delete_observation(im.image_id, idx)


def _check(im: Any, model: Any, T_sfm: Rigid3, cad_from_sfm: Sim3, cfg: CameraRefineConfig) -> RefinedCamera:
    obs = [(p.xy, model.points3D[p.point3D_id].xyz) for p in im.points2D if p.has_point3D()]
    n = len(obs)
    if n == 0:
        return RefinedCamera(T_sfm, False, 0, 0, float("nan"), 0.0, 0.0)
    uv = np.array([o[0] for o in obs], dtype=np.float64)
    Xc = np.array([im.cam_from_world() * o[1] for o in obs], dtype=np.float64)
    front = Xc[:, 2] > 0
    err = np.full(n, np.inf)
    if front.any():
        err[front] = np.linalg.norm(np.asarray(im.camera.img_from_cam(Xc[front])).reshape(-1, 2) - uv[front], axis=1)
    keep = err < cfg.inlier_px
    T = _world_pose(im.cam_from_world(), cad_from_sfm)
    shift = float(np.linalg.norm(T.t - T_sfm.t))
    turn = float(np.degrees(geodesic_angle(T.R, T_sfm.R)))
    ok = keep.sum() >= cfg.min_inliers and shift <= cfg.max_shift_m and turn <= cfg.max_turn_deg
    rms = float(np.sqrt(np.mean(err[keep] ** 2))) if keep.any() else float("nan")
    return RefinedCamera(T if ok else T_sfm, bool(ok), n, int(keep.sum()), rms, shift, turn)


def rays_of(cam) -> np.ndarray:  # noqa: ANN001  (a pycolmap.Camera)
    """(H, W, 3) rays with z = 1 through the pixel centres (COLMAP: first pixel centre at 0.5) of ``cam``."""
    w, h = int(cam.width), int(cam.height)
    uu, vv = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    xy = np.asarray(cam.cam_from_img(np.stack([uu.ravel(), vv.ravel()], 1)), dtype=np.float64)
    return np.concatenate([xy, np.ones((len(xy), 1))], axis=1).reshape(h, w, 3)

"""Improving a first model: pose-guided loop closure and robust refinement.

*Loop closure.* Sequential matching never pairs the end of an orbit with its
start, and COLMAP's own loop detection needs a downloaded vocabulary tree.
Appearance-based retrieval would also be dangerous here: subsea frames are
symmetric, and a view of one side matches the opposite side about as well as a
true neighbour, which folds the model. Instead, :func:`loop_pairs` proposes
pairs the *first model* already puts close together (centres within a few
frame-to-frame steps, similar viewing directions) although they are far apart
in time; those pairs are matched and verified, and the model is rebuilt.

*Robust refinement.* :func:`refine` alternates a Cauchy-loss bundle adjustment
with dropping observations whose reprojection error exceeds a pixel threshold
and points with a small triangulation angle. With murky-water feature noise
(~0.5 px) the mapper's 4 px filter keeps wrong matches (edges sliding along
epipolar lines, silhouettes); removing them halves the pose error.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from cadalign.sfm.colmap_log import stderr_captured
from cadalign.sfm.config import SfMConfig

log = logging.getLogger(__name__)


def loop_pairs(
    names: Sequence[str], centres: np.ndarray, view_dirs: np.ndarray, order: dict[str, int], cfg: SfMConfig
) -> list[tuple[str, str]]:
    """Pairs that are close in space but not matched by the sequential window.

    Args:
        names: (N,) registered frame names.
        centres: (N, 3) camera centres of a first model (any units).
        view_dirs: (N, 3) unit viewing directions (camera z axes in the world).
        order: frame name -> index in capture order (all frames, registered or not).
        cfg: uses ``matching.overlap``, ``loop_num_neighbors``, ``loop_max_distance``, ``loop_max_angle_deg``.

    Returns:
        Sorted, de-duplicated ``(name_a, name_b)`` pairs with ``name_a < name_b``.
    """
    m = cfg.matching
    n = len(names)
    if n < 3:
        return []
    idx = np.argsort([order[x] for x in names])
    steps = np.linalg.norm(np.diff(centres[idx], axis=0), axis=1)
    step = float(np.median(steps)) if len(steps) else 0.0
    if step <= 0:
        return []
    cos_max = np.cos(np.radians(m.loop_max_angle_deg))
    pairs = set()
    for i in range(n):
        dist = np.linalg.norm(centres - centres[i], axis=1)
        for j in np.argsort(dist)[1 : m.loop_num_neighbors + 1]:
            if abs(order[names[i]] - order[names[j]]) <= m.overlap:
                continue
            if dist[j] > m.loop_max_distance * step or float(view_dirs[i] @ view_dirs[j]) < cos_max:
                continue
            pairs.add(tuple(sorted((names[i], names[j]))))
    return sorted(pairs)


def model_loop_pairs(rec: Any, all_names: Sequence[str], cfg: SfMConfig) -> list[tuple[str, str]]:
    """:func:`loop_pairs` for a pycolmap Reconstruction; ``all_names`` in capture order."""
    images = [im for im in rec.images.values() if im.has_pose]
    names = [im.name for im in images]
    centres = np.array([im.projection_center() for im in images]).reshape(-1, 3)
    dirs = np.array([im.viewing_direction() for im in images]).reshape(-1, 3)
    return loop_pairs(names, centres, dirs, {name: k for k, name in enumerate(all_names)}, cfg)


def refine(rec: Any, cfg: SfMConfig) -> dict[str, Any]:
    """Robust bundle adjustment + outlier filtering of ``rec`` in place; returns what it did.

    Each of ``mapper.refine_iterations`` rounds runs a Cauchy-loss bundle adjustment (scale
    ``refine_loss_scale_px``) and then drops observations above ``refine_max_error_px`` and points
    below ``refine_min_tri_angle_deg``. Intrinsics are refined unless a known calibration is fixed.
    """
    import pycolmap  # lazy: heavy dependency (pycolmap)

    mp = cfg.mapper
    fixed = cfg.camera.intrinsics is not None and not cfg.camera.refine_intrinsics
    calibrated = _set_known_intrinsics(rec, cfg)
    before = {"points": rec.num_points3D(), "reprojection_px": rec.compute_mean_reprojection_error()}
    dropped = []
    for _ in range(mp.refine_iterations):
        opts = pycolmap.BundleAdjustmentOptions()
        opts.print_summary = False
        opts.refine_focal_length = not fixed
        opts.refine_extra_params = not fixed
        opts.refine_principal_point = False
        opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        opts.ceres.loss_function_scale = mp.refine_loss_scale_px
        opts.ceres.solver_options.max_num_iterations = mp.refine_max_num_iterations
        opts.ceres.solver_options.num_threads = cfg.num_threads
        opts.ceres.use_gpu = False
        with stderr_captured():  # pycolmap's bundle_adjustment logs at INFO whatever glog's flags say
            pycolmap.bundle_adjustment(rec, opts)
        n = pycolmap.ObservationManager(rec).filter_all_points3D(mp.refine_max_error_px, mp.refine_min_tri_angle_deg)
        dropped.append(int(n))
    after = {"points": rec.num_points3D(), "reprojection_px": rec.compute_mean_reprojection_error()}
    log.info("refinement: %d rounds, points %d -> %d, reprojection %.3f -> %.3f px", mp.refine_iterations,
             before["points"], after["points"], before["reprojection_px"], after["reprojection_px"])
    out = {"rounds": mp.refine_iterations, "observations_dropped": dropped, "before": before, "after": after}
    if calibrated:
        out["known_intrinsics_set"] = calibrated
    return out


def _set_known_intrinsics(rec: Any, cfg: SfMConfig) -> dict[str, Any] | None:
    """With ``camera.known_intrinsics_from == 'refinement'``: replace every self-calibrated camera of ``rec``
    by the known PINHOLE calibration (the adjustment that follows moves poses and points to it); returns the
    parameters before and after, or None when there is nothing to set."""
    import pycolmap  # lazy: heavy dependency (pycolmap)

    if cfg.camera.intrinsics is None or cfg.camera.known_intrinsics_from != "refinement":
        return None
    changed = {}
    for cid, cam in list(rec.cameras.items()):
        changed[str(cid)] = {"model_before": cam.model.name, "params_before": list(map(float, cam.params)),
                             "params_after": list(cfg.camera.intrinsics)}
        rec.cameras[cid] = pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height,
                                           params=list(cfg.camera.intrinsics), camera_id=cid)
    rec.update_point_3d_errors()
    log.info("known calibration set after mapping: %s", "; ".join(
        f"camera {cid}: {c['model_before']} {', '.join(f'{v:.2f}' for v in c['params_before'])} -> PINHOLE "
        f"{', '.join(f'{v:.2f}' for v in c['params_after'])}" for cid, c in changed.items()))
    return changed

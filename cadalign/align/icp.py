"""Sim(3) ICP with a scale guard, then rigid robust point-to-plane refinement.

Why the guard: each Sim(3) ICP step is a Umeyama fit on nearest-neighbour pairs, whose scale is
``s = tr(D S) / var(src)``. Points with no CAD counterpart (seabed, marine growth, a neighbouring
structure) are still paired with the nearest CAD surface when the correspondence distance is large;
those pairs are poorly correlated, which shrinks the cross-covariance and so ``s`` at every step, and a
smaller cloud pairs even more points: the scale runs away towards 0. Three things stop it here: a
shrinking correspondence-distance schedule, trimming of the worst pairs, and a bounded scale (a largest
relative step per iteration and an absolute range around the coarse estimate).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from cadalign.align.config import PointToPlaneConfig, Sim3ICPConfig
from cadalign.align.result import IcpStep
from cadalign.align.surface import CadSurface, query_workers
from cadalign.errors import DegenerateGeometryError
from cadalign.geometry import umeyama
from cadalign.types import Sim3

log = logging.getLogger(__name__)


def subsample(points: np.ndarray, max_points: int, seed: int) -> np.ndarray:
    """At most ``max_points`` rows of ``points`` (N, 3), a seeded random subset in the original order."""
    if len(points) <= max_points:
        return points
    keep = np.sort(np.random.default_rng(seed).choice(len(points), max_points, replace=False))
    return points[keep]


def _pairs(
    y: np.ndarray, surface: CadSurface, max_dist: float, cfg: Sim3ICPConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Trimmed correspondences: (mask into ``y``, targets (K, 3), residuals (K,)) within ``max_dist``."""
    d, idx = surface.tree.query(y, distance_upper_bound=max_dist, workers=query_workers(len(y)))
    ok = np.isfinite(d)
    y_ok, idx_ok = y[ok], idx[ok]
    target = surface.points_m[idx_ok]
    if cfg.point_to_plane_targets:
        n = surface.normals[idx_ok]
        off = np.einsum("ij,ij->i", y_ok - target, n)
        target = y_ok - off[:, None] * n
        res = np.abs(off)
    else:
        res = d[ok]
    if len(res) and cfg.trim_keep < 1.0:
        keep = res <= np.quantile(res, cfg.trim_keep)
        sub = np.flatnonzero(ok)
        ok = np.zeros_like(ok)
        ok[sub[keep]] = True
        target, res = target[keep], res[keep]
    return ok, target, res


def _guard_scale(step: Sim3, s_now: float, s_ref: float, cfg: Sim3ICPConfig) -> tuple[float, bool]:
    """The step's scale after the per-iteration and absolute bounds, and whether they changed it."""
    if not cfg.scale_guard:
        return step.s, False
    s_step = float(np.clip(step.s, 1.0 / (1.0 + cfg.max_scale_step), 1.0 + cfg.max_scale_step))
    s_new = float(np.clip(s_now * s_step, s_ref / cfg.scale_range, s_ref * cfg.scale_range))
    s_step = s_new / s_now
    return s_step, not np.isclose(s_step, step.s, rtol=1e-12, atol=0.0)


def _fit_step(src: np.ndarray, dst: np.ndarray, s_now: float, s_ref: float, cfg: Sim3ICPConfig) -> tuple[Sim3, bool]:
    """Umeyama step ``dst ~ step(src)`` with the scale guarded; the rotation does not depend on the scale,
    so only the translation is recomputed (the least-squares optimum for the clamped scale)."""
    step = umeyama(src, dst, with_scale=True)
    s, clamped = _guard_scale(step, s_now, s_ref, cfg)
    if clamped:
        step = Sim3(s, step.R, dst.mean(axis=0) - s * (step.R @ src.mean(axis=0)))
    return step, clamped


def sim3_icp(
    points_sfm: np.ndarray,
    surface: CadSurface,
    init: Sim3,
    cfg: Sim3ICPConfig,
    *,
    scale_ref: float | None = None,
    schedule_m: Sequence[float] | None = None,
    iters_per_level: int | None = None,
) -> tuple[Sim3, list[IcpStep]]:
    """Refine ``cad_from_sfm`` by point-to-point ICP with scale, coarse to fine.

    Args:
        points_sfm: (N, 3) SfM points (SfM units).
        surface: CAD surface samples (metres) with normals and a KD-tree.
        init: starting ``cad_from_sfm``.
        cfg: ICP knobs; ``cfg.corr_dist_schedule_rel`` times the CAD diameter is the distance schedule
            unless ``schedule_m`` is given.
        scale_ref: centre of the allowed scale range (default ``init.s``).
        schedule_m: explicit correspondence distances per level, metres.
        iters_per_level: overrides ``cfg.iters_per_level``.

    Returns:
        ``(cad_from_sfm, history)``. A level with too few pairs or degenerate pairs is skipped (logged);
        the quality gates judge the outcome.
    """
    schedule = list(schedule_m) if schedule_m is not None else [
        r * surface.diameter_m for r in cfg.corr_dist_schedule_rel]
    n_iter = iters_per_level or cfg.iters_per_level
    s_ref = init.s if scale_ref is None else scale_ref
    tol_m = cfg.tol_rel * surface.diameter_m
    T, history = init, []
    for level, max_dist in enumerate(schedule):
        for it in range(n_iter):
            y = T.apply(points_sfm)
            mask, target, res = _pairs(y, surface, max_dist, cfg)
            if len(res) < cfg.min_pairs:
                log.debug("ICP level %d (%.3g m): only %d pairs; next level", level, max_dist, len(res))
                break
            try:
                step, clamped = _fit_step(y[mask], target, T.s, s_ref, cfg)
            except DegenerateGeometryError as exc:
                log.debug("ICP level %d: degenerate pairs (%s); next level", level, exc)
                break
            T = step @ T
            rmse = float(np.sqrt(np.mean(res**2)))
            history.append(IcpStep("sim3", level, it, float(max_dist), len(res), rmse, T.s, clamped))
            motion = float(np.sqrt(np.mean(np.sum((step.apply(y[mask]) - y[mask]) ** 2, axis=1))))
            if motion < tol_m:
                break
    return T, history


def refine_point_to_plane(
    points_sfm: np.ndarray, surface: CadSurface, init: Sim3, cfg: PointToPlaneConfig
) -> tuple[Sim3, IcpStep | None]:
    """Rigid robust point-to-plane ICP (Open3D) on the scaled cloud; the scale of ``init`` is kept.

    The correspondence distance and kernel scale are ``cfg``'s metric values capped at
    ``cfg.max_corr_dist_rel`` times the CAD diameter.

    Returns:
        ``(cad_from_sfm, summary step)``; the summary is ``None`` when no correspondence was found
        (``init`` is returned unchanged).
    """
    import open3d as o3d  # lazy: heavy dependency (open3d)

    reg = o3d.pipelines.registration
    cap = cfg.max_corr_dist_rel * surface.diameter_m
    max_dist, k = min(cfg.max_corr_dist_m, cap), min(cfg.kernel_scale_m, cap)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(init.apply(points_sfm)))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(surface.points_m))
    dst.normals = o3d.utility.Vector3dVector(surface.normals)
    kernel = reg.TukeyLoss(k) if cfg.kernel == "tukey" else reg.HuberLoss(k)
    res = reg.registration_icp(
        src, dst, max_dist, np.eye(4), reg.TransformationEstimationPointToPlane(kernel),
        reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=cfg.max_iters),
    )
    n_pairs = len(res.correspondence_set)
    if n_pairs == 0:
        log.warning("point-to-plane refinement found no pairs within %.3g m; kept the Sim(3) result", max_dist)
        return init, None
    M = np.asarray(res.transformation)
    T = Sim3(1.0, M[:3, :3], M[:3, 3]) @ init
    return T, IcpStep("refine", 0, cfg.max_iters, max_dist, n_pairs, float(res.inlier_rmse), T.s)

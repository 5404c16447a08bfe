"""Depth refinement: point-to-plane ICP of surface samples of the CAD to the back-projected depth inside the
(eroded) mask, Huber-weighted, correspondences found in the model frame (one k-d tree per model), after an
optional slide of the pose along its viewing ray to the observed depth. Configured by
:class:`cadalign.infer.config.RefineConfig`.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_erosion

from cadalign.infer.config import RefineConfig
from cadalign.infer.model_geom import ModelGeometry
from cadalign.infer.refine.refine_math import apply_twist, clamp_step, huber_weights, pose_prior, small_step, solve_step
from cadalign.types import Rigid3

ICP_DAMPING = 1e-6
"""Relative damping of the ICP normal equations (well conditioned: only guards exact singularity)."""


def masked_depth_points(depth_m: np.ndarray, mask: np.ndarray, K: np.ndarray, max_points: int,
                        rng: np.random.Generator, min_points: int = 0) -> np.ndarray:
    """(N, 3) camera points of valid depth inside the mask eroded by one pixel (mixed edge depths dropped).

    A mask whose interior holds fewer than ``min_points`` valid pixels gives all of its pixels instead: a thin
    part's mask is all edge (the default scene's hot stabs at 11 m: masks of ~33 px, 1 px after erosion), and
    ICP's correspondence gate and Huber loss cope with a few mixed depths better than no depth at all.

    Only the mask's bounding box is looked at (the pixels outside it are not the mask's, so eroding the box with a
    zero border erodes the mask alike); the points and their order are those of the whole frame."""
    mask = np.asarray(mask, bool)
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if len(rows) == 0:
        return np.zeros((0, 3))
    y0, x0 = int(rows[0]), int(cols[0])
    box = (slice(y0, int(rows[-1]) + 1), slice(x0, int(cols[-1]) + 1))
    mask, depth = mask[box], np.asarray(depth_m)[box]
    valid = np.isfinite(depth) & (depth > 0)
    inner = binary_erosion(mask, iterations=1, border_value=0) & valid
    if np.count_nonzero(inner) < min_points:
        inner = mask & valid
    r, c = np.nonzero(inner)
    r, c = r + y0, c + x0
    if len(r) > max_points:
        pick = np.sort(rng.choice(len(r), max_points, replace=False))
        r, c = r[pick], c[pick]
    z = depth_m[r, c].astype(np.float64)
    x = (c + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (r + 0.5 - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1)


def icp_points(depth_m: np.ndarray, mask: np.ndarray, K: np.ndarray, cfg: RefineConfig,
               rng: np.random.Generator | None = None) -> np.ndarray:
    """:func:`masked_depth_points` with the refinement's ``max_depth_points`` / ``min_depth_points`` (the points
    every depth fit of a detection uses; ``rng`` defaults to a fresh one seeded with ``cfg.seed``)."""
    rng = np.random.default_rng(cfg.seed) if rng is None else rng
    return masked_depth_points(depth_m, mask, np.asarray(K, float), cfg.max_depth_points, rng, cfg.min_depth_points)


def depth_along_ray(geom: ModelGeometry, T: Rigid3, K: np.ndarray, depth_m: np.ndarray, mask: np.ndarray,
                    min_shift: float = 0.0, iters: int = 3) -> Rigid3:
    """``T`` moved along the ray through its origin by the median depth offset between the observed depth and the
    model's visible surface (a z-buffer of its camera-facing samples) over the mask's pixels, repeated ``iters``
    times (at a wrong depth the model's pixels meet other parts of the surface, so one step is approximate).

    A first shift below ``min_shift`` (metres) is not applied: small errors are ICP's job.
    """
    for i in range(iters):
        dz = _depth_offset(geom, T, K, depth_m, mask)
        if dz is None or (i == 0 and abs(dz) < min_shift):
            return T
        # moving the origin by s * t changes every depth by about s * t_z (the part is small against its distance)
        T = Rigid3(T.R, T.t * (1.0 + dz / T.t[2]))
    return T


def _depth_offset(geom: ModelGeometry, T: Rigid3, K: np.ndarray, depth_m: np.ndarray, mask: np.ndarray
                  ) -> float | None:
    """Median (observed depth - model front-surface depth) over the mask pixels the model covers; None if too few."""
    p_c = T.apply(geom.samples)
    n_c = geom.sample_normals @ T.R.T
    p_c = p_c[(np.einsum("ij,ij->i", n_c, p_c) < 0) & (p_c[:, 2] > 1e-6)]
    if len(p_c) == 0 or T.t[2] <= 0:
        return None
    h, w = mask.shape
    u = np.floor(K[0, 0] * p_c[:, 0] / p_c[:, 2] + K[0, 2]).astype(np.int64)
    v = np.floor(K[1, 1] * p_c[:, 1] / p_c[:, 2] + K[1, 2]).astype(np.int64)
    inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    u, v, z = u[inside], v[inside], p_c[inside, 2]
    seen = mask[v, u] & np.isfinite(depth_m[v, u]) & (depth_m[v, u] > 0)
    if seen.sum() < 6:
        return None
    pix = v[seen] * w + u[seen]
    zbuf = np.full(h * w, np.inf)
    np.minimum.at(zbuf, pix, z[seen])  # the model's own front surface: self-occluded samples drop out
    front = np.unique(pix)
    return float(np.median(depth_m.reshape(-1)[front] - zbuf[front]))


def refine_depth_icp(geom: ModelGeometry, T_init: Rigid3, K: np.ndarray, depth_m: np.ndarray, mask: np.ndarray,
                     cfg: RefineConfig, iters: int | None = None) -> tuple[Rigid3, int, list[float]]:
    """Point-to-plane ICP of the CAD to the masked depth; returns (pose, iterations run, mean |residual| m).

    With ``cfg.depth_init`` the pose is first slid along its ray to the observed depth (:func:`depth_along_ray`)
    and the ICP prior is centred there."""
    Q = icp_points(depth_m, mask, K, cfg)
    n = cfg.depth_iters if iters is None else iters
    if len(Q) < cfg.min_depth_points or n == 0:
        return T_init, 0, []
    if cfg.depth_init:
        T_init = depth_along_ray(geom, T_init, np.asarray(K, float), depth_m, np.asarray(mask, bool),
                                 cfg.icp_max_corr * geom.diameter_m)
    T, done, costs = _icp(geom, T_init, Q, cfg, n)
    if done == 0:  # nothing within the coarse gate: start again with the model's centre on the points
        T_c = Rigid3(T_init.R, np.median(Q, axis=0) - T_init.R @ geom.samples.mean(0))
        T_c = depth_along_ray(geom, T_c, np.asarray(K, float), depth_m, np.asarray(mask, bool))  # centre -> surface
        T_2, done_2, costs_2 = _icp(geom, T_c, Q, cfg, n)
        if done_2:
            return T_2, done_2, costs_2
    return T, done, costs


def _icp(geom: ModelGeometry, T_init: Rigid3, Q: np.ndarray, cfg: RefineConfig, n: int
         ) -> tuple[Rigid3, int, list[float]]:
    """At most ``n`` point-to-plane ICP iterations of the model at ``T_init`` to the points ``Q`` (camera frame),
    with the pose prior centred on ``T_init``."""
    T, costs, done = T_init, [], 0
    for _ in range(n):
        q_obj = T.inverse().apply(Q)
        dist, j = geom.tree.query(q_obj, distance_upper_bound=cfg.icp_max_corr_start * geom.diameter_m)
        ok = dist < cfg.icp_max_corr * geom.diameter_m
        if ok.mean() < 0.5:  # far from converged: widen the gate (coarse) until most points pair up
            ok = np.isfinite(dist)
        if ok.sum() < 6:
            break
        p_c = T.apply(geom.samples[j[ok]])
        n_c = geom.sample_normals[j[ok]] @ T.R.T
        facing = np.einsum("ij,ij->i", n_c, p_c) < 0  # back-facing samples cannot be seen
        p_c, n_c, q = p_c[facing], n_c[facing], Q[ok][facing]
        if len(q) < 6:
            break
        r = np.einsum("ij,ij->i", n_c, p_c - q)
        J = np.concatenate([np.cross(p_c - T.t, n_c), n_c], axis=1)
        costs.append(float(np.mean(np.abs(r))))
        rp, Jp = pose_prior(T, T_init, cfg, cfg.icp_huber_m)
        step = solve_step(np.concatenate([J, Jp]), np.concatenate([r, rp]),
                      np.concatenate([huber_weights(r, cfg.icp_huber_m), np.ones(6)]), ICP_DAMPING)
        if step is None:
            break
        step = clamp_step(step, geom.diameter_m)
        T = apply_twist(step, T)
        done += 1
        if small_step(step, cfg, geom):
            break
    return T, done, costs


FIT_CAP = 0.1
""":func:`depth_fit`'s default cap on a point's distance, in model diameters."""


def depth_fit(geom: ModelGeometry, T: Rigid3, Q: np.ndarray, cap_m: float | None = None) -> float:
    """Mean distance (m) of the observed points ``Q (N, 3)`` to the model surface at ``T``, each capped at
    ``cap_m``, by default :data:`FIT_CAP` diameters (occluders and background in the mask count, but only so much)."""
    d = geom.tree.query(T.inverse().apply(Q))[0]
    return float(np.mean(np.minimum(d, FIT_CAP * geom.diameter_m if cap_m is None else cap_m)))

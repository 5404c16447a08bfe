"""Refinement of a 6-DoF pose against the CAD model: silhouette/contour alignment and depth ICP.

(a) :func:`refine_silhouette`: damped Gauss-Newton (Levenberg-Marquardt with step acceptance) on the signed
distance transform of the predicted mask, sampled at the projections of the model's outline points: points
on the occluding contour (edges between a front- and a back-facing face) that also lie on the outline of
the model's own rendered silhouette. Each residual is the signed distance (px) of a projected outline point
to the mask boundary, so the outline is pulled onto the zero level set from both sides (a shrunken or
grown silhouette is penalised, unlike a one-sided chamfer); residuals are Huber-weighted and truncated.

(b) :func:`refine_depth_icp`: point-to-plane ICP of surface samples of the CAD to the back-projected depth
inside the (eroded) mask, Huber-weighted, correspondences found in the model frame (one k-d tree per model).

Both update the pose by ``(omega, v)`` (:func:`apply_twist`): a turn about the object's origin in camera axes
and a shift. A point moves as ``X' = X + omega x (X - t) + v``; its projection's Jacobian is
``du/dX [-[X - t]_x, I]``. A Gaussian prior on the deviation from the detector's pose fixes directions the
data do not observe.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.ndimage import binary_erosion

from cadalign.config import bounded
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.model_geom import ModelGeometry, contour_points, project_points, render_silhouette
from cadalign.types import Rigid3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RefineConfig:
    method: Literal["none", "silhouette", "depth", "both"] = "both"
    """Which refinements run: ``both`` = silhouette, then depth ICP when a depth map is given."""
    silhouette_iters: int = bounded(15, ge=0)
    """Gauss-Newton iterations of the contour alignment."""
    depth_iters: int = bounded(10, ge=0)
    """Point-to-plane ICP iterations."""
    min_mask_px: int = bounded(400, ge=1)
    """Silhouette refinement is skipped for smaller masks: their outline says too little about the pose."""
    min_depth_points: int = bounded(50, ge=6)
    """ICP is skipped with fewer valid depth points inside the mask."""
    max_contour_points: int = bounded(400, ge=10)
    """Model contour points per iteration (evenly thinned)."""
    huber_px: float = bounded(2.0, gt=0)
    """Huber threshold of the contour residuals, pixels."""
    trunc_px: float = bounded(25.0, gt=0)
    """Contour residuals longer than this (pixels) are ignored (other objects' edges, occluders)."""
    own_edge_px: float = bounded(0.8, gt=0)
    """A contour point is on the outline when within this (px) of its own rendered silhouette's boundary."""
    max_depth_points: int = bounded(1500, ge=10)
    """Back-projected depth points used by ICP."""
    icp_max_corr: float = bounded(0.1, gt=0)
    """Largest ICP correspondence distance as a fraction of the model diameter."""
    icp_huber_m: float = bounded(0.005, gt=0)
    """Huber threshold of the point-to-plane residuals, metres."""
    prior_t_m: float = bounded(0.05, gt=0)
    """Standard deviation of the prior on the detector's translation (m), for unobserved directions."""
    prior_r_deg: float = bounded(5.0, gt=0)
    """Standard deviation of the prior on the detector's rotation (deg)."""
    icp_max_corr_start: float = bounded(0.5, gt=0)
    """ICP's wide gate (fraction of the diameter), while under half the points pair within ``icp_max_corr``."""
    damping: float = bounded(1e-2, ge=0)
    """Silhouette: Levenberg-Marquardt damping, relative to the mean diagonal of the normal matrix."""
    min_step: float = bounded(1e-6, ge=0)
    """Stop when the update's rotation (rad) and translation / diameter both fall below this."""
    depth_init: bool = True
    """Before ICP, slide the pose along its viewing ray by the median offset between the masked depth and the
    model's visible surface, when that is more than ICP's narrow gate (``icp_max_corr`` diameters). A network's
    translation error is mostly depth (the box size at a few pixels is off by 10 %, i.e. ~1 m at 10 m), far
    beyond ICP's gate and its prior on the detector's pose."""
    yaw_hypotheses: int = bounded(1, ge=1)
    """Depth ICP restarts from the pose turned about the model's z axis by multiples of 360 deg / n, keeping the
    best depth fit (1 = the detector's pose only). Upright parts (valves on a frame) are mostly wrong in yaw
    by more than ICP's basin when a network is unsure."""
    seed: int = 0
    """Seed of the point subsampling."""


ICP_DAMPING = 1e-6
"""Relative damping of the ICP normal equations (well conditioned: only guards exact singularity)."""

PRESETS: dict[str, RefineConfig] = {
    "none": RefineConfig(method="none"),
    "fast": RefineConfig(silhouette_iters=5, depth_iters=5, max_contour_points=200, max_depth_points=600),
    "balanced": RefineConfig(),
    "accurate": RefineConfig(silhouette_iters=30, depth_iters=20, max_contour_points=800, max_depth_points=4000,
                             yaw_hypotheses=4),
}


@dataclass(frozen=True)
class RefineResult:
    """The refined pose, the iterations run per stage, the cost after each iteration and the time taken."""

    T_cam_from_obj: Rigid3
    iterations: dict[str, int] = field(default_factory=dict)
    costs: dict[str, list[float]] = field(default_factory=dict)
    seconds: float = 0.0


def apply_twist(xi: np.ndarray, T: Rigid3) -> Rigid3:
    """The pose turned by ``omega`` about the object's origin (camera axes) and moved by ``v``: ``xi = (omega, v)``.

    ``R' = exp(omega) R``, ``t' = t + v``. Turning about the object rather than the camera keeps rotation and
    translation decoupled for a part many metres away (a camera-centred twist couples them by the distance).
    """
    dR = axis_angle_to_matrix(np.asarray(xi[:3], float))
    return Rigid3(dR @ T.R, T.t + np.asarray(xi[3:], float))


def _proj_jacobian(K: np.ndarray, X: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 2, 6) Jacobian of the projection of camera points X (N, 3) wrt ``(omega, v)`` of :func:`apply_twist`.

    A point moves as ``X' = X + omega x (X - t) + v`` with ``t`` the object's origin in the camera frame.
    """
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    a, b, c = (X - t).T
    iz = 1.0 / z
    du = np.zeros((len(X), 2, 3))
    du[:, 0, 0] = K[0, 0] * iz
    du[:, 0, 2] = -K[0, 0] * x * iz * iz
    du[:, 1, 1] = K[1, 1] * iz
    du[:, 1, 2] = -K[1, 1] * y * iz * iz
    dX = np.zeros((len(X), 3, 6))
    dX[:, 0, 1], dX[:, 0, 2] = c, -b  # -[X - t]_x
    dX[:, 1, 0], dX[:, 1, 2] = -c, a
    dX[:, 2, 0], dX[:, 2, 1] = b, -a
    dX[:, :, 3:] = np.eye(3)
    return du @ dX


def _small(step: np.ndarray, cfg: RefineConfig, geom: ModelGeometry) -> bool:
    return bool(np.linalg.norm(step[:3]) < cfg.min_step and np.linalg.norm(step[3:]) < cfg.min_step * geom.diameter_m)


def _clamp(step: np.ndarray, diameter_m: float) -> np.ndarray:
    """Limit one update to 0.2 rad and a quarter diameter (a guard against a near-singular system)."""
    out = step.copy()
    for sl, lim in ((slice(0, 3), 0.2), (slice(3, 6), 0.25 * diameter_m)):
        n = np.linalg.norm(out[sl])
        if n > lim:
            out[sl] *= lim / n
    return out


def _huber_weights(r: np.ndarray, k: float) -> np.ndarray:
    a = np.abs(r)
    return np.where(a <= k, 1.0, k / np.maximum(a, 1e-12))


def _solve(J: np.ndarray, r: np.ndarray, w: np.ndarray, damping: float) -> np.ndarray | None:
    """Weighted damped Gauss-Newton step ``argmin sum w (r + J xi)^2``; None when under-determined."""
    if len(r) < 6:
        return None
    Jw = J * w[:, None]
    H = Jw.T @ J
    g = Jw.T @ r
    H += damping * np.mean(np.diag(H)) * np.eye(6)
    try:
        return -np.linalg.solve(H, g)
    except np.linalg.LinAlgError:
        return None


@dataclass(frozen=True)
class SignedDistance:
    """Signed distance (px) to a mask's boundary in a window: > 0 outside, < 0 inside, 0 on the boundary.

    The boundary lies halfway between an inside and an outside pixel centre, hence the 0.5 px corrections.
    Outside the image the mask is extended by replicating its border pixels, so an object cut by the
    image border is not outlined there.
    """

    sdf: np.ndarray
    grad: np.ndarray
    offset: np.ndarray

    @staticmethod
    def of(mask: np.ndarray, margin: int) -> SignedDistance:
        import cv2

        m = np.asarray(mask, bool)
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        x0, x1 = cols[0] - margin, cols[-1] + 1 + margin
        y0, y1 = rows[0] - margin, rows[-1] + 1 + margin
        H, W = m.shape
        sub = m[max(y0, 0):min(y1, H), max(x0, 0):min(x1, W)].astype(np.uint8)
        sub = cv2.copyMakeBorder(sub, max(-y0, 0), max(y1 - H, 0), max(-x0, 0), max(x1 - W, 0), cv2.BORDER_REPLICATE)
        d_out = cv2.distanceTransform(1 - sub, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        d_in = cv2.distanceTransform(sub, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        sdf = np.where(sub > 0, 0.5 - d_in, d_out - 0.5).astype(np.float64)
        if not (sub == 0).any():  # the mask fills the window: no boundary anywhere
            sdf = np.full(sub.shape, -float(margin))
        gy, gx = np.gradient(sdf)
        return SignedDistance(sdf, np.stack([gx, gy], -1), np.array([x0, y0], float))

    def sample(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bilinear (values (N,), gradients (N, 2), inside-window flags (N,)) at pixel coordinates (N, 2)."""
        p = uv - 0.5 - self.offset  # array index space: pixel centres at integers
        H, W = self.sdf.shape
        ok = (p[:, 0] >= 0) & (p[:, 1] >= 0) & (p[:, 0] <= W - 1.001) & (p[:, 1] <= H - 1.001)
        p = np.clip(p, 0, [W - 1.001, H - 1.001])
        i0 = np.floor(p).astype(int)
        f = p - i0
        w = [(1 - f[:, 0]) * (1 - f[:, 1]), f[:, 0] * (1 - f[:, 1]), (1 - f[:, 0]) * f[:, 1], f[:, 0] * f[:, 1]]
        idx = [(i0[:, 1], i0[:, 0]), (i0[:, 1], i0[:, 0] + 1), (i0[:, 1] + 1, i0[:, 0]), (i0[:, 1] + 1, i0[:, 0] + 1)]
        val = sum(wk * self.sdf[ix] for wk, ix in zip(w, idx, strict=True))
        grad = sum(wk[:, None] * self.grad[ix] for wk, ix in zip(w, idx, strict=True))
        return val, grad, ok


def _outline_points(geom: ModelGeometry, T: Rigid3, K: np.ndarray, shape: tuple[int, int], cfg: RefineConfig,
                    rng: np.random.Generator) -> np.ndarray:
    """Contour points (model frame) that lie on the outline of the model's own rendered silhouette."""
    P = contour_points(geom, T, K, max_points=4 * cfg.max_contour_points, rng=rng)
    if len(P) == 0:
        return P
    uv = project_points(K, T.apply(P))
    lo = np.floor(uv.min(0)).astype(int) - 3
    hi = np.ceil(uv.max(0)).astype(int) + 3
    if np.any(hi - lo > 4 * max(shape)):  # absurd pose: skip the visibility filter
        return P[: cfg.max_contour_points]
    sil = render_silhouette(geom, T, K, (int(hi[1] - lo[1]), int(hi[0] - lo[0])), (int(lo[0]), int(lo[1])))
    if not sil.any():
        return P[:0]
    own, _, ok = SignedDistance.of(sil, 2).sample(uv - lo)  # window coordinates
    sil_ok = ok & (np.abs(own) <= cfg.own_edge_px)
    P = P[sil_ok]
    if len(P) > cfg.max_contour_points:
        P = P[np.sort(rng.choice(len(P), cfg.max_contour_points, replace=False))]
    return P


def _prior(T: Rigid3, T_init: Rigid3, cfg: RefineConfig, unit: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows (r (6,), J (6, 6)) of the Gaussian prior on the deviation from the detector's pose.

    The deviation is (rotation vector of ``R R_init^T``, ``t - t_init``); a step (omega, v) of
    :func:`apply_twist` changes it by (omega, v) to first order. Scaled by ``unit / sigma``: one sigma costs as
    much as one residual of size ``unit`` (the Huber threshold), negligible where the data constrain the pose,
    decisive where they do not (depth of a small silhouette, the axis of a cylinder in ICP).
    """
    from cadalign.geometry.rotations import matrix_to_axis_angle

    dev = np.concatenate([matrix_to_axis_angle(T.R @ T_init.R.T), T.t - T_init.t])
    S = np.diag([unit / np.radians(cfg.prior_r_deg)] * 3 + [unit / cfg.prior_t_m] * 3)
    return S @ dev, S


def _contour_step(geom: ModelGeometry, T: Rigid3, T_init: Rigid3, K: np.ndarray, sd: SignedDistance,
                  shape: tuple[int, int], cfg: RefineConfig, rng: np.random.Generator,
                  damping: float) -> tuple[np.ndarray | None, float]:
    """One damped Gauss-Newton step on the outline's signed distances plus the prior; (step, cost at ``T``).

    The cost is the mean Huber loss of the outline residuals (truncated at ``trunc_px``) plus the prior term
    divided by the number of residuals, matching the normal equations solved for the step.
    """
    P = _outline_points(geom, T, K, shape, cfg, rng)
    if len(P) < 6:
        return None, float("nan")
    Xc = T.apply(P)
    uv = project_points(K, Xc)
    r, g, ok = sd.sample(uv)
    keep = ok & (np.abs(r) < cfg.trunc_px)
    if keep.sum() < 6:
        return None, float("nan")
    k, a = cfg.huber_px, np.minimum(np.abs(r[ok]), cfg.trunc_px)
    loss = np.where(a <= k, 0.5 * a * a, k * (a - 0.5 * k))
    rp, Jp = _prior(T, T_init, cfg, cfg.huber_px)
    cost = float((loss.sum() + 0.5 * rp @ rp) / max(ok.sum(), 1))
    J = np.einsum("nk,nkj->nj", g[keep], _proj_jacobian(K, Xc[keep], T.t))
    Jall = np.concatenate([J, Jp])
    rall = np.concatenate([r[keep], rp])
    w = np.concatenate([_huber_weights(r[keep], cfg.huber_px), np.ones(6)])
    return _solve(Jall, rall, w, damping), cost


def refine_silhouette(geom: ModelGeometry, T_init: Rigid3, K: np.ndarray, mask: np.ndarray, cfg: RefineConfig,
                      iters: int | None = None) -> tuple[Rigid3, int, list[float]]:
    """Align the projected CAD outline to the boundary of ``mask`` (H, W) bool; returns (pose, iters, costs).

    ``costs`` are the LM costs (see :func:`_contour_step`) of the initial pose and after each accepted update.
    """
    n = cfg.silhouette_iters if iters is None else iters
    if np.count_nonzero(mask) < max(cfg.min_mask_px, 6) or n == 0:
        return T_init, 0, []
    sd = SignedDistance.of(mask, int(np.ceil(cfg.trunc_px)) + 2)
    rng = np.random.default_rng(cfg.seed)
    K = np.asarray(K, float)
    # Levenberg-Marquardt: a step is kept only if the cost (re-measured with fresh outline points) does not
    # grow. Depth along the ray is weakly observed for small silhouettes; the prior keeps it near the
    # detector's estimate instead of drifting at equal cost.
    T, costs, done, lam = T_init, [], 0, cfg.damping
    step, cost = _contour_step(geom, T, T_init, K, sd, mask.shape, cfg, rng, lam)
    for _ in range(n):
        if step is None:
            break
        T_new = apply_twist(step, T)
        step_new, cost_new = _contour_step(geom, T_new, T_init, K, sd, mask.shape, cfg, rng, lam)
        done += 1
        if step_new is not None and cost_new <= cost:
            costs.append(cost)
            small = _small(step, cfg, geom)
            T, step, cost, lam = T_new, step_new, cost_new, max(lam / 3.0, 1e-9)
            if small:
                break
        else:
            lam *= 10.0
            if lam > 1e3:
                break
            step, cost = _contour_step(geom, T, T_init, K, sd, mask.shape, cfg, rng, lam)
    costs.append(cost)
    return T, done, costs


def masked_depth_points(depth_m: np.ndarray, mask: np.ndarray, K: np.ndarray, max_points: int,
                        rng: np.random.Generator) -> np.ndarray:
    """(N, 3) camera points of valid depth inside the mask eroded by one pixel (mixed edge depths dropped)."""
    inner = binary_erosion(np.asarray(mask, bool), iterations=1, border_value=0)
    r, c = np.nonzero(inner & np.isfinite(depth_m) & (depth_m > 0))
    if len(r) > max_points:
        pick = np.sort(rng.choice(len(r), max_points, replace=False))
        r, c = r[pick], c[pick]
    z = depth_m[r, c].astype(np.float64)
    x = (c + 0.5 - K[0, 2]) / K[0, 0] * z
    y = (r + 0.5 - K[1, 2]) / K[1, 1] * z
    return np.stack([x, y, z], axis=1)


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
    rng = np.random.default_rng(cfg.seed)
    Q = masked_depth_points(depth_m, mask, np.asarray(K, float), cfg.max_depth_points, rng)
    n = cfg.depth_iters if iters is None else iters
    if len(Q) < cfg.min_depth_points or n == 0:
        return T_init, 0, []
    if cfg.depth_init:
        T_init = depth_along_ray(geom, T_init, np.asarray(K, float), depth_m, np.asarray(mask, bool),
                                 cfg.icp_max_corr * geom.diameter_m)
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
        rp, Jp = _prior(T, T_init, cfg, cfg.icp_huber_m)
        step = _solve(np.concatenate([J, Jp]), np.concatenate([r, rp]),
                      np.concatenate([_huber_weights(r, cfg.icp_huber_m), np.ones(6)]), ICP_DAMPING)
        if step is None:
            break
        step = _clamp(step, geom.diameter_m)
        T = apply_twist(step, T)
        done += 1
        if _small(step, cfg, geom):
            break
    return T, done, costs


def refine(geom: ModelGeometry, T_init: Rigid3, K: np.ndarray, mask: np.ndarray, cfg: RefineConfig,
           depth_m: np.ndarray | None = None) -> RefineResult:
    """Run the configured refinements in order (silhouette, then depth ICP when ``depth_m`` is given)."""
    t0 = time.perf_counter()
    T, iters, costs = T_init, {}, {}
    if cfg.method in ("silhouette", "both"):
        T, iters["silhouette"], costs["silhouette"] = refine_silhouette(geom, T, K, mask, cfg)
    if cfg.method in ("depth", "both") and depth_m is not None:
        T, iters["depth"], costs["depth"] = _icp_yaw_hypotheses(geom, T, K, depth_m, mask, cfg)
    return RefineResult(T, iters, costs, time.perf_counter() - t0)


def depth_fit(geom: ModelGeometry, T: Rigid3, Q: np.ndarray) -> float:
    """Mean distance (m) of the observed points ``Q (N, 3)`` to the model surface at ``T``, each capped at
    0.1 diameters (occluders and background in the mask count, but only so much)."""
    d = geom.tree.query(T.inverse().apply(Q))[0]
    return float(np.mean(np.minimum(d, 0.1 * geom.diameter_m)))


def _icp_yaw_hypotheses(geom: ModelGeometry, T0: Rigid3, K: np.ndarray, depth_m: np.ndarray, mask: np.ndarray,
                        cfg: RefineConfig) -> tuple[Rigid3, int, list[float]]:
    best = refine_depth_icp(geom, T0, K, depth_m, mask, cfg)
    if cfg.yaw_hypotheses <= 1 or best[1] == 0:
        return best
    Q = masked_depth_points(depth_m, mask, np.asarray(K, float), cfg.max_depth_points, np.random.default_rng(cfg.seed))
    score = depth_fit(geom, best[0], Q)
    for k in range(1, cfg.yaw_hypotheses):
        yaw = axis_angle_to_matrix(np.array([0.0, 0.0, 2 * np.pi * k / cfg.yaw_hypotheses]))
        cand = refine_depth_icp(geom, Rigid3(T0.R @ yaw, T0.t), K, depth_m, mask, cfg)
        s = depth_fit(geom, cand[0], Q)
        if s < score:
            best, score = cand, s
    return best


def silhouette_iou(geom: ModelGeometry, T: Rigid3, K: np.ndarray, mask: np.ndarray) -> float:
    """IoU of the model's rendered silhouette at ``T`` with ``mask`` (H, W) (used to pick among candidates)."""
    sil = render_silhouette(geom, T, np.asarray(K, float), mask.shape)
    union = np.count_nonzero(sil | mask)
    return float(np.count_nonzero(sil & mask) / union) if union else 0.0

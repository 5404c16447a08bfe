"""Silhouette refinement: the projected CAD outline pulled onto the boundary of the predicted mask.

Damped Gauss-Newton (Levenberg-Marquardt with step acceptance) on the signed distance transform of the mask,
sampled at the projections of the model's outline points: points on the occluding contour (edges between a
front- and a back-facing face) that also lie on the outline of the model's own rendered silhouette. Each
residual is the signed distance (px) of a projected outline point to the mask boundary, so the outline is
pulled onto the zero level set from both sides (a shrunken or grown silhouette is penalised, unlike a one-sided
chamfer); residuals are Huber-weighted and truncated. Configured by :class:`cadalign.infer.config.RefineConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cadalign.geometry.compare import mask_iou
from cadalign.infer.config import RefineConfig
from cadalign.infer.model_geom import ModelGeometry, contour_points, project_points, render_silhouette
from cadalign.infer.refine.refine_math import (
    apply_twist,
    huber_weights,
    pose_prior,
    proj_jacobian,
    small_step,
    solve_step,
)
from cadalign.types import Rigid3


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
    rp, Jp = pose_prior(T, T_init, cfg, cfg.huber_px)
    cost = float((loss.sum() + 0.5 * rp @ rp) / max(ok.sum(), 1))
    J = np.einsum("nk,nkj->nj", g[keep], proj_jacobian(K, Xc[keep], T.t))
    Jall = np.concatenate([J, Jp])
    rall = np.concatenate([r[keep], rp])
    w = np.concatenate([huber_weights(r[keep], cfg.huber_px), np.ones(6)])
    return solve_step(Jall, rall, w, damping), cost


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
            small = small_step(step, cfg, geom)
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


def silhouette_iou(geom: ModelGeometry, T: Rigid3, K: np.ndarray, mask: np.ndarray) -> float:
    """IoU of the model's rendered silhouette at ``T`` with ``mask`` (H, W) (used to pick among candidates)."""
    return mask_iou(render_silhouette(geom, T, np.asarray(K, float), mask.shape), mask)

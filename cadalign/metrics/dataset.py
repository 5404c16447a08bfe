"""Accuracy of generated ground truth against exact (simulated) truth: depth, masks, poses, alignment.

Mask IoU is :func:`cadalign.geometry.compare.mask_iou` (re-exported here; 0 for two empty masks, which the dataset
evaluation never compares: it scores only objects with at least 50 visible true pixels)."""

from __future__ import annotations

import numpy as np

from cadalign.geometry.compare import mask_iou as mask_iou
from cadalign.geometry.compare import rotation_error_deg
from cadalign.types import Rigid3, Sim3


def depth_errors(pred_m: np.ndarray, true_m: np.ndarray, region: np.ndarray | None = None) -> dict[str, float]:
    """Coverage and errors of a depth map (0 / non-finite = invalid) against true depth on ``region``.

    Returns ``coverage`` (fraction of region pixels with a valid prediction), ``abs_rel``
    (mean |p - t| / t), ``rmse_m`` and ``delta1`` (fraction with max(p/t, t/p) < 1.25), all over pixels
    valid in both; NaN errors when there are none.
    """
    true_ok = np.isfinite(true_m) & (true_m > 0)
    region = true_ok if region is None else (region & true_ok)
    pred_ok = np.isfinite(pred_m) & (pred_m > 0) & region
    n_region = int(region.sum())
    out = {"coverage": float(pred_ok.sum() / n_region) if n_region else 0.0, "n_pixels": int(pred_ok.sum())}
    if not pred_ok.any():
        return {**out, "abs_rel": float("nan"), "rmse_m": float("nan"), "delta1": float("nan")}
    p, t = pred_m[pred_ok].astype(np.float64), true_m[pred_ok].astype(np.float64)
    ratio = np.maximum(p / t, t / p)
    return {**out, "abs_rel": float(np.mean(np.abs(p - t) / t)), "rmse_m": float(np.sqrt(np.mean((p - t) ** 2))),
            "delta1": float(np.mean(ratio < 1.25))}


def boundary_offset_px(truth: np.ndarray, est: np.ndarray) -> tuple[float, float]:
    """(outline offset, mean width) of a mask ``est`` against ``truth``, both in pixels.

    The offset is the area where the masks disagree divided by the true outline's length (its boundary
    pixels): how far, on average, the estimated outline lies from the true one. A shift or growth of one
    pixel all round reads ~1 whatever the part's size, whereas IoU punishes thin parts: a part 3 px wide
    loses IoU 0.2 to an outline a third of a pixel off, a large one keeps 0.99. The width is ``2 A / P``
    of the true mask. (nan, 0) for an empty ``truth``.
    """
    m, e = np.asarray(truth, dtype=bool), np.asarray(est, dtype=bool)
    inner = m.copy()
    inner[1:] &= m[:-1]
    inner[:-1] &= m[1:]
    inner[:, 1:] &= m[:, :-1]
    inner[:, :-1] &= m[:, 1:]
    perimeter = float((m & ~inner).sum())
    if perimeter == 0:
        return float("nan"), 0.0
    return float((m ^ e).sum()) / perimeter, 2 * float(m.sum()) / perimeter


def pose_errors(est: Rigid3, true: Rigid3) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) between two poses."""
    return float(rotation_error_deg(est.R, true.R)), float(np.linalg.norm(est.t - true.t))


def sim3_errors(est: Sim3, true: Sim3, at_points: np.ndarray) -> dict[str, float]:
    """Errors of an estimated ``cad_from_sfm`` against the true one.

    Rotation in degrees, relative scale error, and translation error measured where it matters: the
    RMS displacement (metres) of ``at_points`` (SfM points on the structure) between the two maps.
    """
    d = est.apply(at_points) - true.apply(at_points)
    return {
        "rotation_deg": float(rotation_error_deg(est.R, true.R)),
        "scale_rel": float(abs(est.s / true.s - 1.0)),
        "translation_m": float(np.sqrt(np.mean(np.sum(d**2, axis=1)))),
    }

"""Eigen et al. depth metrics with the evaluation protocol (crop, cap, alignment) stated in the result.

Over the evaluated pixels (valid ground truth inside the crop and inside ``(min_depth_m, max_depth_m]``), with
prediction ``d`` and truth ``g`` in metres:

- AbsRel = mean(|d - g| / g), SqRel = mean((d - g)² / g), RMSE = sqrt(mean((d - g)²)),
- RMSElog = sqrt(mean((ln d - ln g)²)), δ<1.25^k = fraction with max(d/g, g/d) < 1.25^k, k = 1, 2, 3.

Before that the prediction is optionally scaled by ``median(g) / median(d)`` (``alignment="median"``, for
scale-ambiguous predictions) and clamped to ``[min_depth_m, max_depth_m]`` (the "cap"). A set of frames is
summarised as the mean of the per-frame metrics (the KITTI/Eigen convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from cadalign.config import bounded
from cadalign.errors import InputError

METRICS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "delta1", "delta2", "delta3")


@dataclass(frozen=True)
class DepthEvalConfig:
    min_depth_m: float = bounded(1e-3, gt=0)
    """Ground truth at or below this is ignored; predictions are clamped up to it."""
    max_depth_m: float = bounded(80.0, gt=0)
    """The cap: ground truth above it is ignored, predictions are clamped down to it."""
    alignment: Literal["none", "median"] = "none"
    """``none``: metric depth as predicted; ``median``: per-frame median scaling before the metrics."""
    crop: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)
    """Evaluated window as fractions ``(top, bottom, left, right)`` of the image; (0, 1, 0, 1) = full frame."""

    def protocol(self) -> dict:
        """The protocol as a JSON dict, written beside every result."""
        return {"crop_fraction_top_bottom_left_right": list(self.crop), "cap_m": [self.min_depth_m, self.max_depth_m],
                "alignment": self.alignment, "averaging": "mean over frames of per-frame metrics",
                "pixels": "ground truth > 0, inside the crop and the cap"}


def depth_errors(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """The seven Eigen metrics of matching 1-D arrays of positive depths (no masking, alignment or cap).

    >>> e = depth_errors(np.array([2.0, 1.0]), np.array([1.0, 1.0]))
    >>> e["abs_rel"], e["rmse"], e["delta1"]
    (0.5, 0.7071067811865476, 0.5)
    """
    pred = np.asarray(pred, dtype=np.float64).ravel()
    gt = np.asarray(gt, dtype=np.float64).ravel()
    if pred.shape != gt.shape:
        raise InputError(f"prediction has {pred.size} values, ground truth {gt.size}")
    if pred.size == 0:
        return dict.fromkeys(METRICS, math.nan)
    if (pred <= 0).any() or (gt <= 0).any():
        raise InputError("depth_errors needs positive depths; mask invalid pixels first")
    ratio = np.maximum(pred / gt, gt / pred)
    diff = pred - gt
    return {
        "abs_rel": float(np.mean(np.abs(diff) / gt)),
        "sq_rel": float(np.mean(diff**2 / gt)),
        "rmse": float(np.sqrt(np.mean(diff**2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(pred) - np.log(gt)) ** 2))),
        "delta1": float(np.mean(ratio < 1.25)),
        "delta2": float(np.mean(ratio < 1.25**2)),
        "delta3": float(np.mean(ratio < 1.25**3)),
    }


def eval_mask(gt: np.ndarray, cfg: DepthEvalConfig, extra: np.ndarray | None = None) -> np.ndarray:
    """(H, W) bool: pixels evaluated under ``cfg`` (valid, in the cap, in the crop, and in ``extra`` if given)."""
    h, w = gt.shape
    t, b, lft, r = cfg.crop
    crop = np.zeros((h, w), dtype=bool)
    crop[int(round(t * h)) : int(round(b * h)), int(round(lft * w)) : int(round(r * w))] = True
    mask = crop & (gt > cfg.min_depth_m) & (gt <= cfg.max_depth_m) & np.isfinite(gt)
    return mask & extra.astype(bool) if extra is not None else mask


def frame_depth_errors(pred: np.ndarray, gt: np.ndarray, cfg: DepthEvalConfig,
                       extra_mask: np.ndarray | None = None) -> tuple[dict[str, float], int]:
    """Metrics of one (H, W) frame under ``cfg``; returns (metrics, evaluated pixel count)."""
    if pred.shape != gt.shape:
        raise InputError(f"prediction {pred.shape} and ground truth {gt.shape} differ in shape")
    mask = eval_mask(gt, cfg, extra_mask)
    p, g = np.asarray(pred, dtype=np.float64)[mask], np.asarray(gt, dtype=np.float64)[mask]
    if p.size and cfg.alignment == "median":
        p = p * (np.median(g) / max(np.median(p), 1e-12))
    p = np.clip(np.nan_to_num(p, nan=cfg.min_depth_m), cfg.min_depth_m, cfg.max_depth_m)
    return depth_errors(p, g), int(mask.sum())


class DepthAccumulator:
    """Mean over frames of per-frame metrics (frames with no evaluated pixel are skipped and counted)."""

    def __init__(self) -> None:
        self.rows: list[dict[str, float]] = []
        self.pixels = 0
        self.empty_frames = 0

    def add(self, metrics: dict[str, float], pixels: int) -> None:
        if pixels == 0:
            self.empty_frames += 1
            return
        self.rows.append(metrics)
        self.pixels += pixels

    def summary(self) -> dict[str, float | int]:
        out: dict[str, float | int] = {k: float(np.mean([r[k] for r in self.rows])) if self.rows else math.nan
                                       for k in METRICS}
        out.update(frames=len(self.rows), empty_frames=self.empty_frames, pixels=self.pixels)
        return out

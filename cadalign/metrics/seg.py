"""Semantic segmentation metrics from a confusion matrix: per-class IoU, mIoU, pixel accuracy.

``confusion[i, j]`` counts pixels of ground-truth class ``i`` predicted as class ``j``; pixels labelled
``ignore_index`` are not counted. IoU of class c is ``TP / (TP + FP + FN)``; it is NaN (undefined) when the
class appears neither in the ground truth nor in the prediction, and mIoU is the mean over the defined ones.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from cadalign.errors import InputError

IGNORE = 255


def confusion_matrix(pred: np.ndarray, label: np.ndarray, n_classes: int, ignore_index: int = IGNORE) -> np.ndarray:
    """``(n_classes, n_classes)`` int64 counts (rows: ground truth, columns: prediction) of two label maps.

    >>> confusion_matrix(np.array([0, 1, 1]), np.array([0, 0, 1]), 2).tolist()
    [[1, 1], [0, 1]]
    """
    pred = np.asarray(pred)
    label = np.asarray(label)
    if pred.shape != label.shape:
        raise InputError(f"prediction shape {pred.shape} differs from label shape {label.shape}")
    keep = label != ignore_index
    p, g = pred[keep].astype(np.int64), label[keep].astype(np.int64)
    if p.size and (p.min() < 0 or p.max() >= n_classes or g.min() < 0 or g.max() >= n_classes):
        raise InputError(f"class indices must lie in [0, {n_classes}) (or be {ignore_index} in the label)")
    return np.bincount(g * n_classes + p, minlength=n_classes**2).reshape(n_classes, n_classes)


@dataclass(frozen=True)
class SegMetrics:
    classes: tuple[str, ...]
    """Class names, index 0 background."""
    iou: tuple[float, ...]
    """Per-class IoU (NaN where the class is neither labelled nor predicted)."""
    miou: float
    """Mean of the defined per-class IoUs (background included)."""
    miou_fg: float
    """Mean of the defined per-class IoUs without the background (class 0)."""
    pixel_accuracy: float
    """Correct pixels / labelled pixels."""
    pixels: int
    """Labelled pixels counted."""
    confusion: tuple[tuple[int, ...], ...]
    """Rows: ground truth, columns: prediction."""

    def to_json(self) -> dict:
        """A JSON-safe dict (NaN -> None) with a name -> IoU table."""
        clean = [None if math.isnan(v) else v for v in self.iou]
        return {
            "iou": dict(zip(self.classes, clean, strict=True)),
            "miou": None if math.isnan(self.miou) else self.miou,
            "miou_foreground": None if math.isnan(self.miou_fg) else self.miou_fg,
            "pixel_accuracy": self.pixel_accuracy,
            "pixels": self.pixels,
            "confusion": [list(r) for r in self.confusion],
            "confusion_axes": "rows: ground truth, columns: prediction",
        }


def seg_metrics(confusion: np.ndarray, classes: Sequence[str]) -> SegMetrics:
    """Per-class IoU, mIoU and pixel accuracy of a confusion matrix.

    >>> m = seg_metrics(np.array([[3, 1], [0, 2]]), ["bg", "valve"])
    >>> [round(v, 4) for v in m.iou], round(m.pixel_accuracy, 4)
    ([0.75, 0.6667], 0.8333)
    """
    cm = np.asarray(confusion, dtype=np.int64)
    if cm.shape != (len(classes), len(classes)):
        raise InputError(f"confusion matrix {cm.shape} does not match {len(classes)} classes")
    tp = np.diag(cm).astype(np.float64)
    denom = cm.sum(0) + cm.sum(1) - np.diag(cm)
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = np.where(denom > 0, tp / np.maximum(denom, 1), np.nan)
    total = int(cm.sum())
    return SegMetrics(
        classes=tuple(classes),
        iou=tuple(float(v) for v in iou),
        miou=_nanmean(iou),
        miou_fg=_nanmean(iou[1:]),
        pixel_accuracy=float(tp.sum() / total) if total else math.nan,
        pixels=total,
        confusion=tuple(tuple(int(v) for v in r) for r in cm),
    )


def _nanmean(v: np.ndarray) -> float:
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else math.nan

"""Segmentation and depth losses, safe on empty masks (they return a zero that still carries a gradient).

Shapes: logits ``(B, C, H, W)``, labels ``(B, H, W)`` int64 with ``ignore_index`` for unlabelled pixels;
depth maps ``(B, 1, H, W)`` metres with a boolean ``valid`` mask of the same shape.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

IGNORE = 255
"""Label value of pixels that no loss or metric counts."""


def _zero_like(x: torch.Tensor) -> torch.Tensor:
    """A scalar 0 connected to ``x``'s graph (so backward works and nothing becomes NaN)."""
    return x.sum() * 0.0


def cross_entropy(logits: torch.Tensor, labels: torch.Tensor, weight: torch.Tensor | None = None,
                  ignore_index: int = IGNORE, gamma: float = 0.0,
                  pixel_weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean (class-weighted) cross-entropy over labelled pixels; 0 when no pixel is labelled.

    With ``gamma > 0`` each pixel's term is scaled by ``(1 - p_true)**gamma`` (focal loss, Lin et al.), so
    the many easy background pixels count less; the mean is still normalised by the summed class weights
    of the labelled pixels, as ``F.cross_entropy`` does. ``pixel_weight`` (B, H, W) multiplies each pixel's
    weight (e.g. :func:`boundary_weights`) in both the sum and the normalisation.
    """
    valid = labels != ignore_index
    if not bool(valid.any()):
        return _zero_like(logits)
    if gamma == 0 and pixel_weight is None:
        return F.cross_entropy(logits.float(), labels, weight=weight, ignore_index=ignore_index)
    ce = F.cross_entropy(logits.float(), labels, ignore_index=ignore_index, reduction="none")[valid]
    w = weight[labels[valid]] if weight is not None else torch.ones_like(ce)
    if pixel_weight is not None:
        w = w * pixel_weight[valid].to(w.dtype)
    focal = (1.0 - torch.exp(-ce)).clamp_min(0) ** gamma if gamma > 0 else torch.ones_like(ce)
    return (w * focal * ce).sum() / w.sum().clamp_min(1e-12)


def boundary_weights(labels: torch.Tensor, boost: float, radius: int = 1,
                     ignore_index: int = IGNORE) -> torch.Tensor:
    """Per-pixel weights ``1 + boost`` within ``radius`` pixels (Chebyshev) of another class, else 1.

    ``labels`` (B, H, W) int; ignored pixels neither count as another class nor get boosted. Thin parts
    (1-2 px bars) lie wholly on a boundary, so they are boosted all along. Returns (B, H, W) float32.

    >>> boundary_weights(torch.tensor([[[0, 0, 1, 1]]]), 2.0).tolist()
    [[[1.0, 3.0, 3.0, 1.0]]]
    """
    lab = labels.long()
    valid = lab != ignore_index
    k = 2 * radius + 1
    big = torch.iinfo(torch.int32).max
    hi = F.max_pool2d(torch.where(valid, lab, -1).float()[:, None], k, stride=1, padding=radius)[:, 0]
    lo = -F.max_pool2d(torch.where(valid, -lab, -big).float()[:, None], k, stride=1, padding=radius)[:, 0]
    edge = valid & (hi > lo)
    return 1.0 + boost * edge.float()


def soft_dice(logits: torch.Tensor, labels: torch.Tensor, ignore_index: int = IGNORE, eps: float = 1.0) -> torch.Tensor:
    """1 - mean soft Dice over the classes present in ``labels`` or predicted (background included).

    Each class' Dice is ``(2*sum(p*y) + eps) / (sum(p) + sum(y) + eps)`` over labelled pixels, ``p`` the softmax.
    """
    valid = labels != ignore_index
    if not bool(valid.any()):
        return _zero_like(logits)
    n = logits.shape[1]
    prob = logits.float().softmax(1) * valid[:, None]
    onehot = F.one_hot(labels.clamp(0, n - 1) * valid, n).permute(0, 3, 1, 2).float() * valid[:, None]
    inter = (prob * onehot).sum((0, 2, 3))
    denom = prob.sum((0, 2, 3)) + onehot.sum((0, 2, 3))
    dice = (2 * inter + eps) / (denom + eps)
    present = onehot.sum((0, 2, 3)) > 0
    return 1.0 - dice[present].mean() if bool(present.any()) else _zero_like(logits)


def median_frequency_weights(counts: np.ndarray, image_counts: np.ndarray) -> np.ndarray:
    """Median-frequency class weights (Eigen & Fergus): ``median(f) / f_c``.

    Args:
        counts: (C,) pixels of each class over the training set.
        image_counts: (C,) pixels of the images in which each class appears.

    Returns:
        (C,) weights; a class that never appears gets weight 0 (no pixel to weigh).

    >>> median_frequency_weights(np.array([90, 10]), np.array([100, 100])).round(3).tolist()
    [0.556, 5.0]
    """
    counts = np.asarray(counts, dtype=np.float64)
    image_counts = np.asarray(image_counts, dtype=np.float64)
    present = counts > 0
    freq = np.where(present, counts / np.maximum(image_counts, 1), np.nan)
    med = np.nanmedian(freq) if present.any() else 1.0
    return np.where(present, med / np.where(present, freq, 1.0), 0.0)


def masked_mse(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean squared error over valid pixels (metres²); 0 with a gradient when none is valid."""
    if not bool(valid.any()):
        return _zero_like(pred)
    return ((pred.float() - target.float())[valid] ** 2).mean()


def masked_l1(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean absolute error over valid pixels (metres)."""
    if not bool(valid.any()):
        return _zero_like(pred)
    return (pred.float() - target.float())[valid].abs().mean()


def scale_invariant_log(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor, lam: float = 0.85,
                        eps: float = 1e-6) -> torch.Tensor:
    """Eigen's scale-invariant log loss ``sqrt(mean(d²) - lam*mean(d)²)``, ``d = log pred - log target``.

    ``lam = 0`` is the plain log RMSE; ``lam = 1`` is fully scale invariant. Per batch over valid pixels.
    """
    valid = valid & (target > eps)
    if not bool(valid.any()):
        return _zero_like(pred)
    d = torch.log(pred.float()[valid].clamp_min(eps)) - torch.log(target.float()[valid])
    return torch.sqrt((d**2).mean() - lam * d.mean() ** 2 + eps)


def gradient_loss(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Mean L1 difference of the x/y finite differences of log depth, over pixel pairs valid on both sides."""
    valid = valid & (target > eps)
    lp = torch.log(pred.float().clamp_min(eps))
    lt = torch.log(target.float().clamp_min(eps))
    total, count = _zero_like(pred), 0
    for dim in (-1, -2):
        n = lp.shape[dim]
        pair = valid.narrow(dim, 1, n - 1) & valid.narrow(dim, 0, n - 1)
        if bool(pair.any()):
            dp = lp.narrow(dim, 1, n - 1) - lp.narrow(dim, 0, n - 1)
            dt = lt.narrow(dim, 1, n - 1) - lt.narrow(dim, 0, n - 1)
            total = total + (dp - dt)[pair].abs().sum()
            count += int(pair.sum())
    return total / count if count else total

"""Comparisons of two estimates: rotation error, box IoU and mask IoU (one implementation each, numpy only).

The metrics (:mod:`cadalign.metrics.pose`, :mod:`cadalign.metrics.dataset`) and the stages that
score candidates (:mod:`cadalign.infer`) call these. Boxes are ``x0, y0, x1, y1`` in pixels with ``x1``/``y1``
exclusive (pixel-edge coordinates of :mod:`cadalign.types`).

The IoU of two empty boxes or masks is 0: nothing was found where there is nothing, which is not a match (the
rule of the BOP and COCO toolkits; an IoU of 1 would count it as a perfect one).
"""

from __future__ import annotations

import numpy as np

from cadalign.errors import InputError
from cadalign.geometry.rotations import geodesic_angle

__all__ = ["box_iou", "mask_iou", "rotation_error_deg"]


def rotation_error_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray | float:
    """Angle (degrees) of the rotation between ``R_a`` and ``R_b`` ((..., 3, 3), broadcast): the geodesic distance.

    Symmetry-aware errors (a part that a turn leaves unchanged) are
    :func:`cadalign.metrics.pose.rotation_error_deg`.

    >>> from cadalign.geometry.rotations import axis_angle_to_matrix
    >>> round(float(rotation_error_deg(np.eye(3), axis_angle_to_matrix(np.array([0, 0, np.pi / 6])))), 6)
    30.0
    """
    return np.degrees(geodesic_angle(R_a, R_b))


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU of boxes ``a`` (N, 4) and ``b`` (M, 4), xyxy pixels; returns (N, M), 0 for empty boxes.

    >>> box_iou(np.array([[0, 0, 2, 2]]), np.array([[1, 1, 3, 3], [0, 0, 2, 2], [5, 5, 5, 5]]))
    array([[0.14285714, 1.        , 0.        ]])
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1, 4)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 4)
    area_a = np.clip(a[:, 2] - a[:, 0], 0, None) * np.clip(a[:, 3] - a[:, 1], 0, None)
    area_b = np.clip(b[:, 2] - b[:, 0], 0, None) * np.clip(b[:, 3] - b[:, 1], 0, None)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=-1)
    union = area_a[:, None] + area_b[None, :] - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """IoU of two masks of the same shape (non-zero = inside); 0 when both are empty.

    Raises:
        InputError: the shapes differ.

    >>> a = np.zeros((4, 4), bool); a[:2] = True
    >>> b = np.zeros((4, 4), bool); b[1:3] = True
    >>> mask_iou(a, b), mask_iou(a, a), mask_iou(~a & a, ~a & a)
    (0.3333333333333333, 1.0, 0.0)
    """
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    if a.shape != b.shape:
        raise InputError(f"mask shapes differ: {a.shape} vs {b.shape}")
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else 0.0

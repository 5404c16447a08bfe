"""Predicted depth and class probabilities for fusion, from ``cadalign train seg|depth`` runs.

Adapters from :mod:`cadalign.infer.dense` to the small callables fusion consumes
(:data:`~cadalign.fuse.inputs.SegPredictor`, :data:`~cadalign.fuse.inputs.DepthPredictor`), so any other
model can be plugged in by passing a function instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cadalign.errors import InputError
from cadalign.fuse.inputs import DepthPredictor, SegPredictor
from cadalign.types import Camera


def seg_predictor(run: Path, classes: Sequence[str], device: str = "cpu") -> SegPredictor:
    """``rgb -> (C, H, W)`` probabilities of the segmentation network of ``run`` (its classes must match)."""
    from cadalign.infer.dense import load_dense_model, seg_probabilities

    dm = load_dense_model(Path(run), task="seg", classes=classes, device=device)

    def predict(rgb: np.ndarray) -> np.ndarray:
        return seg_probabilities(dm, rgb)[0].numpy()

    return predict


def depth_predictor(run: Path, seg: SegPredictor | None = None, device: str = "cpu") -> DepthPredictor:
    """``(rgb, camera) -> (H, W)`` metric depth of the depth network of ``run``.

    A network trained with a foreground-mask input gets ``seg``'s prediction (class != background) as mask.
    """
    from cadalign.infer.dense import load_dense_model, metric_depth

    dm = load_dense_model(Path(run), task="depth", device=device)
    if dm.mask_input and seg is None:
        raise InputError(f"{dm.checkpoint} was trained with a foreground-mask input: also pass --model-seg RUN "
                         "so the mask can be predicted")

    def predict(rgb: np.ndarray, camera: Camera) -> np.ndarray:
        fg = (seg(rgb).argmax(axis=0) != 0) if dm.mask_input and seg is not None else None
        return metric_depth(dm, rgb, fg)[0].numpy()

    return predict

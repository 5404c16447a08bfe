"""Predicted depth and class probabilities for fusion, from ``cadalign train seg|depth`` runs.

Adapters from :mod:`cadalign.infer.dense` to the small callables fusion consumes
(:data:`~cadalign.fuse.inputs.SegPredictor`, :data:`~cadalign.fuse.inputs.DepthPredictor`), so any other
model can be plugged in by passing a function instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.errors import InputError
from cadalign.fuse.inputs import DepthPredictor, SegPredictor
from cadalign.sfm import image_prep
from cadalign.types import Camera


def _feed(run: Path, source_prep: dict[str, Any] | None) -> dict[str, Any]:
    """What the frames (prepared as ``source_prep``, None: unknown) need before ``run``'s network sees them
    (:mod:`cadalign.sfm.image_prep`): raw frames get the enhancement its training images had."""
    return image_prep.to_feed(source_prep, image_prep.read_run_prep(run), str(run))


def seg_predictor(run: Path, classes: Sequence[str] | None, device: str = "cpu",
                  source_prep: dict[str, Any] | None = None) -> SegPredictor:
    """``rgb -> (C, H, W)`` probabilities of the segmentation network of ``run`` (its classes must match
    ``classes``; None: the network's own classes, unchecked).

    ``source_prep``: how the frames to be fed were prepared (:func:`cadalign.sfm.image_prep.read_prep` of their
    scene); raw frames are then prepared as the network's training images were. The last result is remembered
    (keyed by the image object), so the depth mask and the labels of one frame share one network pass.
    """
    from cadalign.infer.dense import load_dense_model, seg_probabilities  # lazy: pulls torch

    dm = load_dense_model(Path(run), task="seg", classes=classes, device=device)
    prep = _feed(run, source_prep)
    last: list = [None, None]

    def predict(rgb: np.ndarray) -> np.ndarray:
        if last[0] is not rgb:
            last[0], last[1] = rgb, seg_probabilities(dm, image_prep.apply(rgb, prep))[0].numpy()
        return last[1]

    return predict


def depth_predictor(run: Path, seg: SegPredictor | None = None, device: str = "cpu",
                    foreground_only: bool = False, source_prep: dict[str, Any] | None = None) -> DepthPredictor:
    """``(rgb, camera) -> (H, W)`` metric depth of the depth network of ``run``; ``source_prep`` as for
    :func:`seg_predictor` (``seg`` prepares its own input).

    A network trained with a foreground-mask input gets ``seg``'s prediction (class != background) as mask.
    ``foreground_only`` zeroes (invalidates) the depth wherever ``seg`` predicts background: depth networks
    predict a depth for open water too, which would otherwise be fused as surfaces.
    """
    from cadalign.infer.dense import load_dense_model, metric_depth  # lazy: pulls torch

    dm = load_dense_model(Path(run), task="depth", device=device)
    prep = _feed(run, source_prep)
    if dm.mask_input and seg is None:
        raise InputError(f"{dm.checkpoint} was trained with a foreground-mask input: also pass --model-seg RUN "
                         "so the mask can be predicted (fuse, emulate; infer has no segmentation model to give, "
                         "so use a depth network trained without the mask input there)")

    if foreground_only and seg is None:
        raise InputError("fusing only the foreground of predicted depth needs a segmentation model (--model-seg)")

    def predict(rgb: np.ndarray, camera: Camera) -> np.ndarray:
        fg = (seg(rgb).argmax(axis=0) != 0) if seg is not None and (dm.mask_input or foreground_only) else None
        depth = metric_depth(dm, image_prep.apply(rgb, prep), fg if dm.mask_input else None)[0].numpy()
        return np.where(fg, depth, 0.0).astype(np.float32) if foreground_only else depth

    return predict

"""Evaluate trained segmentation / depth networks on a split of a BOP dataset; metrics JSON + PNG panels.

Predictions are made at the network's training scale and upsampled to the full frame (see
:mod:`cadalign.infer.dense`); metrics are computed at the full ground-truth resolution. The JSON states the
protocol: resolution handling, ignored pixels, and for depth the crop, cap and alignment.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from cadalign.infer.dense import load_dense_model, metric_depth, seg_probabilities
from cadalign.io import write_image, write_json
from cadalign.metrics.depth import DepthAccumulator, DepthEvalConfig, frame_depth_errors
from cadalign.metrics.seg import confusion_matrix, seg_metrics
from cadalign.train.data import select
from cadalign.train.datasets import DepthDataset, SegmentationDataset

log = logging.getLogger(__name__)

PALETTE = np.array([[0, 0, 0], [70, 130, 220], [240, 200, 40], [230, 60, 60], [60, 200, 90], [200, 90, 220],
                    [255, 140, 0], [0, 210, 210]], dtype=np.uint8)


@dataclass(frozen=True)
class EvalOutput:
    metrics_path: Path
    """The metrics JSON."""
    metrics: dict
    """Its content."""
    figures: tuple[Path, ...]
    """The PNG panels written."""


def colour_labels(label: np.ndarray) -> np.ndarray:
    """(H, W) class indices -> (H, W, 3) uint8 colours (cycled palette; ignored pixels white)."""
    out = PALETTE[np.asarray(label) % len(PALETTE)]
    out[np.asarray(label) == 255] = 255
    return out


def colour_depth(depth: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(H, W) metres -> (H, W, 3) uint8 (turbo colour map over [lo, hi]; invalid <= 0 black)."""
    from matplotlib import colormaps  # lazy: heavy dependency (matplotlib)

    t = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)
    rgb = (colormaps["turbo"](t)[..., :3] * 255).astype(np.uint8)
    rgb[~(depth > 0)] = 0
    return rgb


def _vis_ids(n: int, k: int) -> set[int]:
    return set(np.unique(np.linspace(0, n - 1, min(n, k)).round().astype(int)).tolist()) if n else set()


def evaluate_seg(run: Path, ds: Path, out: Path, *, split: str = "test", device: str = "cpu",
                 n_vis: int = 4, flip_tta: bool = False) -> EvalOutput:
    """Per-class IoU, mIoU and pixel accuracy of the model in ``run`` on ``split`` of ``ds``; writes ``out``.

    ``flip_tta`` averages each frame's probabilities with those of its mirror image (stated in the protocol).
    """

    sel = select(ds, split)
    data = SegmentationDataset(sel.scene_dir, sel.ids)
    dm = load_dense_model(run, task="seg", classes=data.classes.names, device=device)
    n = len(dm.classes)
    cm = np.zeros((n, n), dtype=np.int64)
    figs, vis = [], _vis_ids(len(data), n_vis)
    for i in range(len(data)):
        item = data[i]
        pred = seg_probabilities(dm, item["image"], flip_tta=flip_tta)[0].argmax(0).numpy()
        label = item["label"].numpy()
        cm += confusion_matrix(pred, label, n)
        if i in vis:
            img = (item["image"].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
            panel = np.concatenate([img, colour_labels(label), colour_labels(pred)], axis=1)
            figs.append(write_image(Path(out) / f"seg_{item['im_id']:06d}.png", panel))
    m = seg_metrics(cm, dm.classes)
    result = {
        "task": "seg", "model": str(dm.checkpoint), "steps": dm.steps,
        "dataset": {"scene": str(sel.scene_dir), "split": split, "frames": len(sel.ids), "source": sel.source},
        "protocol": {"resolution": f"network at scale {dm.scale}, logits upsampled bilinearly to the full frame",
                     "pixels": "every labelled pixel of the full frame (label 255 ignored)", "crop": "none",
                     "test_time_augmentation": "mean of the frame and its mirror" if flip_tta else "none"},
        **m.to_json(),
        "figures": "image | ground truth | prediction",
    }
    path = write_json(Path(out) / "seg_metrics.json", result)
    ious = ", ".join(f"{c} {float(v):.3f}" for c, v in zip(m.classes, m.iou, strict=True))
    log.info("seg %s: mIoU %.3f, IoU %s", split, float(m.miou), ious)
    return EvalOutput(path, result, tuple(figs))


def evaluate_depth(run: Path, ds: Path, out: Path, *, split: str = "test", device: str = "cpu",
                   cfg: DepthEvalConfig | None = None, n_vis: int = 4) -> EvalOutput:
    """Eigen depth metrics of the model in ``run`` on ``split`` of ``ds``: over all valid pixels and per class.

    Per-class rows restrict the pixels to those the ground-truth class map gives that class (e.g. structure).
    A model with a mask input gets the ground-truth foreground mask (stated in the protocol).
    """

    cfg = cfg or DepthEvalConfig()
    sel = select(ds, split)
    data = DepthDataset(sel.scene_dir, sel.ids)
    labels = SegmentationDataset(sel.scene_dir, sel.ids)
    dm = load_dense_model(run, task="depth", device=device)
    names = data.classes.names
    acc = {"all": DepthAccumulator(), **{c: DepthAccumulator() for c in names[1:]}}
    figs, vis = [], _vis_ids(len(data), n_vis)
    for i in range(len(data)):
        item = data[i]
        label = labels[i]["label"].numpy()
        pred = metric_depth(dm, item["image"], fg_mask=torch.from_numpy(label > 0) if dm.mask_input else None)
        pred_np, gt = pred[0].numpy().astype(np.float64), item["depth"][0].numpy().astype(np.float64)
        acc["all"].add(*frame_depth_errors(pred_np, gt, cfg))
        for c, name in enumerate(names[1:], start=1):
            acc[name].add(*frame_depth_errors(pred_np, gt, cfg, extra_mask=label == c))
        if i in vis:
            figs.append(_depth_panel(Path(out) / f"depth_{item['im_id']:06d}.png", item["image"], gt, pred_np))
    result = {
        "task": "depth", "model": str(dm.checkpoint), "steps": dm.steps,
        "dataset": {"scene": str(sel.scene_dir), "split": split, "frames": len(sel.ids), "source": sel.source},
        "protocol": {**cfg.protocol(),
                     "resolution": f"network at scale {dm.scale}, depth upsampled bilinearly to the full frame",
                     "classes": "per-class rows restrict to ground-truth class pixels",
                     "mask_input": "ground-truth foreground" if dm.mask_input else "none"},
        "metrics": {k: a.summary() for k, a in acc.items()},
        "figures": "image | ground truth | prediction | |pred-gt|/gt (0..0.3)",
    }
    path = write_json(Path(out) / "depth_metrics.json", result)
    s = result["metrics"]["all"]
    log.info("depth %s: AbsRel %.3f, delta1 %.3f over %d frames", split, s["abs_rel"], s["delta1"], s["frames"])
    return EvalOutput(path, result, tuple(figs))


def _depth_panel(path: Path, image: torch.Tensor, gt: np.ndarray, pred: np.ndarray) -> Path:
    valid = gt > 0
    lo, hi = (float(np.percentile(gt[valid], 1)), float(np.percentile(gt[valid], 99))) if valid.any() else (0, 1)
    err = np.where(valid, np.abs(pred - gt) / np.where(valid, gt, 1), 0.0)
    from matplotlib import colormaps  # lazy: heavy dependency (matplotlib)

    err_rgb = (colormaps["magma"](np.clip(err / 0.3, 0, 1))[..., :3] * 255).astype(np.uint8)
    err_rgb[~valid] = 0
    img = (image.permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    return write_image(path, np.concatenate([img, colour_depth(gt, lo, hi), colour_depth(pred, lo, hi), err_rgb], 1))

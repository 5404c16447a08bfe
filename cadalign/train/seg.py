"""Semantic segmentation training (ResUNet): config, presets, loss step and ``train_seg``.

The class list comes from the dataset (``objects.json``), never from the code. The loss is cross-entropy,
optionally with median-frequency class weights (clipped at ``max_class_weight``) and a soft-Dice term, which
keeps small classes such as hot stabs from being ignored.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.distributed as dist
from torch import nn

from cadalign.config import bounded
from cadalign.models.resunet import ResUNet, ResUNetConfig
from cadalign.sfm.image_prep import read_prep
from cadalign.train.augment import AugmentConfig, augment_dense, random_patches
from cadalign.train.common import write_run_record
from cadalign.train.data import ScaledDataset, class_pixel_counts, select
from cadalign.train.datasets import SegmentationDataset
from cadalign.train.loop import LoopConfig, TrainResult, augment_seed, train_loop
from cadalign.train.losses import boundary_weights, cross_entropy, median_frequency_weights, soft_dice

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SegTrainConfig:
    model: ResUNetConfig = ResUNetConfig()
    """Network width and depth."""
    loop: LoopConfig = LoopConfig()
    """Optimisation: steps, batch size, learning rate, checkpoints, seed."""
    augment: AugmentConfig = AugmentConfig()
    """Colour/turbidity jitter, flips, crops."""
    scale: float = bounded(0.5, gt=0, le=1)
    """Image scale the network sees (0.5: 640x480 frames become 320x240); predictions are upsampled back."""
    class_weighting: Literal["none", "median_frequency"] = "median_frequency"
    """Cross-entropy class weights."""
    max_class_weight: float = bounded(10.0, ge=1)
    """Clip of the median-frequency weights (a class seen in a few pixels must not dominate)."""
    rare_class_share: float = bounded(0.0, ge=0, lt=1)
    """Classes with fewer than this share of the training pixels are *rare* and capped at
    ``max_rare_class_weight`` instead of ``max_class_weight`` (0 = off). Meant for parts of a few pixels (hot
    stabs: 0.04 % of the default scene's training pixels, valves 0.8 %), which a common cap treats like the valves."""
    max_rare_class_weight: float = bounded(4.0, ge=1)
    """Clip of the weights of the rare classes (see ``rare_class_share``)."""
    dice_weight: float = bounded(0.5, ge=0)
    """Weight of the soft-Dice term added to the cross-entropy (0 = off)."""
    val_every: int = bounded(0, ge=0)
    """Steps between validation mIoU rows (0: only at the end); needs a non-empty val split."""
    patch: tuple[int, int] | None = None
    """Train on random (height, width) windows of the scaled frames (whole frames at inference); None = off."""
    focus_prob: float = bounded(0.5, ge=0, le=1)
    """Share of patches centred on a pixel of a random present non-background class (small classes)."""
    focus_power: float = bounded(0.0, ge=0)
    """Focus classes are drawn with probability proportional to (training pixels of the class)^-focus_power
    among those present in the frame: 0 = uniform, 0.5 = rarer classes (hot stabs) centred more often."""
    class_weight_power: float = bounded(1.0, ge=0)
    """Exponent applied to the median-frequency weights before clipping (0.5 = square-root weights: a
    gentler push that over-predicts small classes less when focus patches already oversample them)."""
    focal_gamma: float = bounded(0.0, ge=0)
    """Focal-loss exponent on the cross-entropy (0 = plain cross-entropy)."""
    boundary_boost: float = bounded(0.0, ge=0)
    """Extra cross-entropy weight of pixels within ``boundary_radius`` of another class (0 = off): pixel weight
    ``1 + boundary_boost`` there. Thin parts (1-2 px hot-stab bars) lie wholly on boundaries. (Boost 2 in a
    150-step fine-tune of the fast model changed no IoU by more than 0.003 on the default scene.)"""
    boundary_radius: int = bounded(1, ge=1, le=5)
    """Chebyshev radius, pixels, of the boundary band boosted by ``boundary_boost``."""
    full_frame_fraction: float = bounded(0.0, ge=0, le=1)
    """Share of the steps, at the end, that train on whole frames instead of ``patch`` windows (0 = never):
    the network finishes on the inference input size and class mix. A share, so ``--steps`` scales it.
    (0.1 on the 1750-step fast preset: val IoU unchanged, test valve 0.752 -> 0.747, hot stab 0.100 -> 0.067.)"""
    full_frame_batch: int = bounded(1, ge=1)
    """Frames per step in that final phase (the first ones of each batch): 1 frame of 640x480 holds the pixels
    of 4 240x320 windows, so a step costs about the same."""
    zoom_prob: float = bounded(0.0, ge=0, le=1)
    """Share of ``patch`` windows zoomed in (:func:`cadalign.train.augment.random_patches`): a smaller window round the
    same centre upsampled to ``patch``, for close-up sizes. 0 = off: worse valves and no hot-stab gain on the default
    scene (docs/tuning/train_config.md#segtrainconfigzoom_prob)."""
    zoom_max: float = bounded(2.0, ge=1)
    """Largest zoom factor (log-uniform in [1, zoom_max])."""
    channels_last: bool = True
    """Train in the channels-last memory layout: the same network and loss, ~25 % less CPU time per step on one thread
    (docs/tuning/train_config.md#segtrainconfigchannels_last)."""


# fast: full-resolution 176x240 windows, 80 % of them centred on a pixel of a small class drawn by inverse pixel
# frequency (hot stabs most often), square-root median-frequency weights capped at 2, and at 4 for classes under
# 0.1 % of the training pixels (hot stabs 0.04 %, valves 0.8 % on the default scene), focal cross-entropy (gamma 2)
# plus Dice 1.0, bf16 autocast where native, channels-last. 3000 steps in 981-1022 CPU-s (one thread, ~17 min).
# Default scene (1 frame/s, fresh-clone demo build), held-out test block, IoU structure/valve/hot stab, seeds
# 0-3: 0.960/0.790/0.556, 0.963/0.796/0.563, 0.962/0.827/0.566, 0.963/0.804/0.545; val block hot stab
# 0.477-0.492. The former recipe (training/seg_fast_s10.toml: 70 % windows by square-root frequency, one cap
# of 2) gave test 0.965/0.817/0.527 and 0.963/0.808/0.492 for seeds 0/1: it predicted 0.78x the hot-stab
# pixels (recall 0.58-0.62), this one 0.90-0.97x (recall 0.69-0.71, precision 0.72-0.76 against 0.76-0.78),
# valves 0.98-1.01x. Screened first on a GPU (3 seeds each, same build): a hot-stab cap of 4 alone and the
# inverse-frequency windows alone each gave ~+0.06 hot-stab IoU at mid-training, Dice 2.0 nothing.
# The thesis-style weights (cap 10 on every class) over-predict valves 2.6x; weights of 1 under-predict them.
# ``eval seg --flip-tta`` adds +0.002..0.03 IoU. History: training/seg_fast_240x320.toml (240x320 windows x 1750
# steps, same CPU time), training/seg_fast_fp32.toml (no autocast: ~1.6x the CPU time, same IoU within the seed
# noise).
PRESETS: dict[str, SegTrainConfig] = {
    "fast": SegTrainConfig(model=ResUNetConfig(base_channels=12), scale=1.0, patch=(176, 240), focus_prob=0.8,
                           focus_power=1.0, class_weight_power=0.5, max_class_weight=2.0, rare_class_share=0.001,
                           max_rare_class_weight=4.0, dice_weight=1.0, focal_gamma=2.0,
                           loop=LoopConfig(steps=3000, batch_size=4, lr=3e-3, checkpoint_every=100, log_every=10,
                                           amp=True)),
    "balanced": SegTrainConfig(model=ResUNetConfig(base_channels=32), scale=1.0, patch=(240, 320),
                               loop=LoopConfig(steps=3000, batch_size=8, lr=2e-3, checkpoint_every=250, log_every=25)),
    "accurate": SegTrainConfig(model=ResUNetConfig(base_channels=48), scale=1.0, val_every=1000,
                               loop=LoopConfig(steps=10000, batch_size=8, lr=1e-3, checkpoint_every=500,
                                               log_every=50)),
}


def class_weights(counts: np.ndarray, image_counts: np.ndarray, cfg: SegTrainConfig) -> np.ndarray | None:
    """The cross-entropy class weights of ``cfg`` from the training labels' pixel counts, or None.

    ``counts``/``image_counts`` are those of :func:`cadalign.train.data.class_pixel_counts`.
    """
    if cfg.class_weighting == "none":
        return None
    counts = np.asarray(counts, dtype=np.float64)
    share = counts / max(counts.sum(), 1.0)
    cap = np.where((counts > 0) & (share < cfg.rare_class_share), cfg.max_rare_class_weight, cfg.max_class_weight)
    w = np.minimum(median_frequency_weights(counts, image_counts) ** cfg.class_weight_power, cap)
    return np.where(counts > 0, np.maximum(w, 1.0 / cfg.max_class_weight), 0.0)


def focus_weights(counts: np.ndarray, cfg: SegTrainConfig) -> list[float] | None:
    """Per-class focus-patch weights ``counts**-focus_power`` (0 for absent classes), or None for uniform."""
    if cfg.focus_power == 0:
        return None
    c = np.asarray(counts, dtype=np.float64)
    return np.where(c > 0, np.maximum(c, 1.0) ** -cfg.focus_power, 0.0).tolist()


def seg_step(weight: torch.Tensor | None, dice_weight: float, gamma: float = 0.0,
             channels_last: bool = False, boundary: tuple[float, int] = (0.0, 1)) -> Callable:
    """The loop's step function: ``(model, batch) -> (CE [+ dice_weight * Dice], {"ce", "dice", "acc"})``.

    ``gamma > 0`` makes the cross-entropy a focal loss; ``boundary = (boost, radius)`` weighs pixels near a
    class boundary ``1 + boost`` in it (see :func:`cadalign.train.losses.boundary_weights`);
    ``channels_last`` feeds the image in that layout.
    """

    def step(model: nn.Module, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        image = batch["image"]
        logits = model(image.contiguous(memory_format=torch.channels_last) if channels_last else image)
        w = weight.to(logits.device) if weight is not None else None
        pw = boundary_weights(batch["label"], boundary[0], boundary[1]) if boundary[0] > 0 else None
        ce = cross_entropy(logits, batch["label"], w, gamma=gamma, pixel_weight=pw)
        metrics = {"ce": float(ce.detach())}
        loss = ce
        if dice_weight > 0:
            dice = soft_dice(logits, batch["label"])
            loss = ce + dice_weight * dice
            metrics["dice"] = float(dice.detach())
        metrics["acc"] = float((logits.detach().argmax(1) == batch["label"]).float().mean())
        return loss, metrics

    return step


def val_miou(ds: ScaledDataset, classes: tuple[str, ...], device: str, batch: int = 4) -> Callable:
    """A ``val_fn`` for the loop: mIoU, foreground mIoU and per-class IoU on ``ds`` at the training scale."""

    n = len(classes)

    def fn(model: nn.Module) -> dict[str, float]:
        cm = np.zeros(n * n, dtype=np.int64)  # the full metrics live in cadalign.evaluate; IoU is all we log here
        for i in range(0, len(ds), batch):
            items = [ds[j] for j in range(i, min(i + batch, len(ds)))]
            pred = model(torch.stack([it["image"] for it in items]).to(device)).argmax(1).cpu()
            lab = torch.stack([it["label"] for it in items])
            keep = lab < n
            cm += np.bincount((lab[keep] * n + pred[keep]).numpy(), minlength=n * n)
        cm = cm.reshape(n, n)
        with np.errstate(invalid="ignore", divide="ignore"):
            iou = np.diag(cm) / (cm.sum(0) + cm.sum(1) - np.diag(cm))
        out = {"miou": float(np.nanmean(iou)), "miou_fg": float(np.nanmean(iou[1:]))}
        out.update({f"iou_{c}": float(v) for c, v in zip(classes, iou, strict=True)})
        return out

    return fn


def augment_step(g: torch.Generator, seed: int) -> int:
    """The loop step whose augmentation generator ``g`` is (inverts :func:`cadalign.train.loop.augment_seed`,
    which is linear in the step), so a resumed run switches phases at the same step as an uninterrupted one."""

    rank = dist.get_rank() if dist.is_available() and dist.is_initialized() else 0
    base = augment_seed(seed, 0, rank)
    step, rest = divmod(g.initial_seed() - base, augment_seed(seed, 1, rank) - base)
    assert rest == 0 and step >= 0, "generator not seeded by the training loop"
    return step


def _patches(batch: dict, g: torch.Generator, cfg: SegTrainConfig, focus: list[float] | None) -> dict:
    full = int(round(cfg.full_frame_fraction * cfg.loop.steps))
    if full and augment_step(g, cfg.loop.seed) >= cfg.loop.steps - full:
        k = min(cfg.full_frame_batch, len(batch["image"]))
        return {key: v[:k] if isinstance(v, torch.Tensor) and v.ndim > 0 and len(v) == len(batch["image"]) else v
                for key, v in batch.items()}
    if cfg.patch is None:
        return batch
    return random_patches(batch, g, cfg.patch, cfg.focus_prob, focus, zoom_prob=cfg.zoom_prob, zoom_max=cfg.zoom_max)


def lamp_weights(focus: list[float] | None, n_classes: int) -> list[float]:
    """Class weights of the lamp-hotspot centre: the focus weights (uniform without them), background excluded."""
    w = list(focus) if focus is not None else [1.0] * n_classes
    return [0.0, *w[1:]]


def train_seg(cfg: SegTrainConfig, ds: Path, out: Path, *, split: str = "train", val_split: str | None = "val",
              resume: bool = False, overwrite: bool = False, device: str = "cpu",
              progress: Callable[[int, int, dict[str, float]], None] | None = None) -> TrainResult:
    """Train a ResUNet on the ``split`` frames of ``ds`` into the run folder ``out`` (see cadalign.train.loop).

    ``out/train_config.json`` records the resolved config, class list, class weights and data selection; the
    checkpoint carries the class list and model config, and resuming with other ones is refused.
    """

    sel = select(ds, split)
    base = SegmentationDataset(sel.scene_dir, sel.ids)
    classes = base.classes.names
    data = ScaledDataset(base, cfg.scale)
    counts, image_counts = class_pixel_counts(data, len(classes))
    weights, focus = class_weights(counts, image_counts, cfg), focus_weights(counts, cfg)
    lamp = lamp_weights(focus, len(classes))
    torch.manual_seed(cfg.loop.seed)
    model = ResUNet(len(classes), cfg.model)
    if cfg.channels_last:
        model = model.to(memory_format=torch.channels_last)
    identity = {"task": "seg", "classes": list(classes), "model": cfg.model, "scale": cfg.scale}
    write_run_record(out, "seg", cfg, identity, {"class_weights": None if weights is None else weights.tolist(),
                                                 "focus_weights": focus, "class_pixels": counts.tolist(),
                                                 "dataset": {"scene": str(sel.scene_dir), "split": split,
                                                             "ids": list(sel.ids), "source": sel.source},
                                                 "images": read_prep(sel.scene_dir)},
                     resume=resume, overwrite=overwrite)
    log.info("seg: %d %s frames of %s, classes %s, weights %s", len(sel.ids), split, sel.scene_dir, classes,
             None if weights is None else np.round(weights, 2).tolist())
    val_fn = None
    if val_split:
        try:
            vsel = select(ds, val_split)
            val_fn = val_miou(ScaledDataset(SegmentationDataset(vsel.scene_dir, vsel.ids), cfg.scale), classes, device)
        except Exception as exc:  # no val frames: train without validation rows
            log.info("no validation (%s)", exc)
    w = None if weights is None else torch.tensor(weights, dtype=torch.float32)
    step = seg_step(w, cfg.dice_weight, cfg.focal_gamma, cfg.channels_last, (cfg.boundary_boost, cfg.boundary_radius))
    return train_loop(model, step, data, cfg.loop, out,
                      augment=(lambda b, g: augment_dense(_patches(b, g, cfg, focus), g, cfg.augment, lamp)),
                      val_fn=val_fn, val_every=cfg.val_every, resume=resume, device=device, progress=progress,
                      extra_state=identity)

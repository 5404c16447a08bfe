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
from torch import nn

from cadalign.config import bounded
from cadalign.data.image_prep import read_prep
from cadalign.models.resunet import ResUNet, ResUNetConfig
from cadalign.train.augment import AugmentConfig, augment_dense, random_patches
from cadalign.train.common import write_run_record
from cadalign.train.data import ScaledDataset, class_pixel_counts, select
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
    """Share of ``patch`` windows zoomed in (see :func:`cadalign.train.augment.random_patches`): a smaller window
    around the same (focus) centre, upsampled to ``patch``, so parts are also seen at close-up sizes. 0 = off.
    (0.5 with zoom_max 2, together with augment.lamp_prob 0.5 / lamp_gain 2.5, on the 1750-step fast preset,
    default-scene build, seed 0: val IoU structure/valve/hot stab 0.954/0.719/0.403, test 0.946/0.638/0.052,
    against 0.957/0.800/0.457 and 0.943/0.752/0.100 without: worse valves, no hot-stab gain.)"""
    zoom_max: float = bounded(2.0, ge=1)
    """Largest zoom factor (log-uniform in [1, zoom_max])."""
    channels_last: bool = True
    """Train in the channels-last memory layout: the same network and loss, ~25 % less CPU time per step on
    one thread (measured: 0.74 -> 0.55 s for a batch of 4 240x320 windows at width 12)."""


# fast: full-resolution 176x240 windows, 70% of them centred on a small-class pixel (hot stabs most often),
# square-root median-frequency weights capped at 2, focal cross-entropy (gamma 2) plus Dice 1.0. The thesis-style
# weights (cap 10) over-predict valves 2.6x on the built default scene; weights of 1 under-predict them; this mix
# predicts ~1.1x. Channels-last layout. 3000 steps of 176x240 cost what 1750 of 240x320 did (the step cost follows
# the window area; measured back to back on the loaded shared 2-core machine: 1614 / 1553 CPU-s for seeds 0 / 1
# against 1684 for 240x320 x 1750, which took 1139-1147 CPU-s under a lighter load: <= 20 CPU-minutes there).
# Calibrated default-scene build, IoU structure/valve/hot stab, seed 0: val 0.966/0.787/0.540, test
# 0.958/0.736/0.136; seed 1: val 0.966/0.808/0.466, test 0.959/0.759/0.042 (240x320 x 1750, training/
# seg_fast_240x320.toml: seed 0 val 0.957/0.800/0.457, test 0.943/0.752/0.100; seed 1 val valve/hot stab
# 0.793/0.511, test 0.732/0.080): structure +0.016, valve and hot stab equal within the seed noise. Test-block
# hot stabs stay <= 0.14: the network misses hot_stab_2's thin bar along a beam even on training frames (train
# hot-stab IoU 0.31), so it is under-fitted, not only out of distribution. ``eval seg --flip-tta`` adds
# +0.002..0.027 valve IoU.
# bf16 autocast (loop.amp, on CPUs with native bf16: AVX512-BF16 or AMX; elsewhere fp32): one thread, quiet
# machine, 3000 steps in 990-1018 CPU-s (user+sys, ~17 min) against 1557 in fp32 (26 min); the same seeds on
# the same default-scene build: seed 0 val 0.966/0.780/0.546, test 0.958/0.736/0.098; seed 1 val
# 0.966/0.815/0.544, test 0.959/0.713/0.080 (fp32 above); on the two-lap capture (datasets/scenes/two_pass.toml)
# test 0.961/0.784/0.502 and 0.960/0.794/0.565 against fp32 0.962/0.796/0.527 and 0.961/0.780/0.502.
# training/seg_fast_fp32.toml is the fp32 run.
PRESETS: dict[str, SegTrainConfig] = {
    "fast": SegTrainConfig(model=ResUNetConfig(base_channels=12), scale=1.0, patch=(176, 240), focus_prob=0.7,
                           focus_power=0.5, class_weight_power=0.5, max_class_weight=2.0, dice_weight=1.0,
                           focal_gamma=2.0,
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
    w = np.minimum(median_frequency_weights(counts, image_counts) ** cfg.class_weight_power, cfg.max_class_weight)
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
        cm = np.zeros(n * n, dtype=np.int64)  # the full metrics live in cadalign.eval; IoU is all we log here
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
    import torch.distributed as dist

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
              resume: bool = False, device: str = "cpu",
              progress: Callable[[int, int, dict[str, float]], None] | None = None) -> TrainResult:
    """Train a ResUNet on the ``split`` frames of ``ds`` into the run folder ``out`` (see cadalign.train.loop).

    ``out/train_config.json`` records the resolved config, class list, class weights and data selection; the
    checkpoint carries the class list and model config, and resuming with other ones is refused.
    """
    from cadalign.data.torch_datasets import SegmentationDataset

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
                     resume=resume)
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

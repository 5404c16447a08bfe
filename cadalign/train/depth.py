"""Monocular metric depth training (DispNet-style): config, presets, masked multi-scale loss, ``train_depth``.

The depth head ``1/(alpha*sigmoid(x)+beta)`` is set from a depth range: ``min_depth_m``/``max_depth_m`` when
given, else from the training frames' 1st/99th depth percentiles widened by ``range_margin``; the resolved
``alpha``/``beta`` are part of the saved model config. Losses count valid pixels only (ground truth > 0);
the coarser predictions are compared with a valid-aware average-pooled ground truth.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from cadalign.config import bounded
from cadalign.models.dispnet import DispNet, DispNetConfig, alpha_beta_from_range
from cadalign.sfm.image_prep import read_prep
from cadalign.train.augment import AugmentConfig, augment_dense
from cadalign.train.common import write_run_record
from cadalign.train.data import ScaledDataset, depth_percentiles, select
from cadalign.train.datasets import DepthDataset
from cadalign.train.loop import LoopConfig, TrainResult, train_loop
from cadalign.train.losses import gradient_loss, masked_l1, masked_mse, scale_invariant_log

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DepthTrainConfig:
    model: DispNetConfig = DispNetConfig()
    """Network width/levels; alpha/beta are replaced by the depth range below unless use_model_alpha_beta."""
    loop: LoopConfig = LoopConfig()
    """Optimisation: steps, batch size, learning rate, checkpoints, seed."""
    augment: AugmentConfig = AugmentConfig()
    """Colour/turbidity jitter, flips, crops (crops rescale the depth targets)."""
    scale: float = bounded(0.5, gt=0, le=1)
    """Image scale the network sees; predictions are upsampled back to the frame size."""
    min_depth_m: float | None = None
    """Nearest depth the head can output, metres (None: from the training data)."""
    max_depth_m: float | None = None
    """Farthest depth the head can output, metres (None: from the training data)."""
    range_margin: float = bounded(1.5, ge=1)
    """Data-derived range: [p1 / margin, p99 * margin] of the training depths."""
    use_model_alpha_beta: bool = False
    """Keep model.alpha/model.beta as given (the thesis' 7.203, 0.935) instead of deriving them."""
    loss: Literal["mse", "l1", "silog"] = "mse"
    """Per-pixel loss: MSE in metres (the thesis), L1, or Eigen's scale-invariant log loss."""
    silog_lambda: float = bounded(0.85, ge=0, le=1)
    """lambda of the scale-invariant log loss (0: log RMSE)."""
    grad_weight: float = bounded(0.0, ge=0)
    """Weight of the log-depth gradient-matching loss (0 = off)."""
    scale_weights: tuple[float, ...] = (1.0, 0.5, 0.25, 0.125)
    """Loss weight of the prediction at each scale, finest first (DispNet's multi-scale supervision)."""
    mask_input: bool = False
    """Feed a 4th input channel: the foreground (non-background class) mask, ground truth while training."""


PRESETS: dict[str, DepthTrainConfig] = {
    "fast": DepthTrainConfig(model=DispNetConfig(base_channels=16, levels=5), scale=0.5, loss="l1",
                             grad_weight=0.5,
                             loop=LoopConfig(steps=1500, batch_size=4, lr=2e-3, checkpoint_every=250, log_every=25)),
    "balanced": DepthTrainConfig(model=DispNetConfig(base_channels=32, levels=6), scale=0.5, grad_weight=0.5,
                                 loop=LoopConfig(steps=4000, batch_size=8, lr=1e-3, checkpoint_every=500,
                                                 log_every=25)),
    "accurate": DepthTrainConfig(model=DispNetConfig(base_channels=32, levels=6), scale=1.0, grad_weight=0.5,
                                 loop=LoopConfig(steps=12000, batch_size=8, lr=1e-3, checkpoint_every=1000,
                                                 log_every=50)),
}


def resolve_model_config(cfg: DepthTrainConfig, train_ds: ScaledDataset) -> DispNetConfig:
    """The DispNet config with the input channels and the depth head's alpha/beta resolved."""
    model = replace(cfg.model, in_channels=4 if cfg.mask_input else 3)
    if cfg.use_model_alpha_beta:
        return model
    lo, hi = cfg.min_depth_m, cfg.max_depth_m
    if lo is None or hi is None:
        p1, p99 = depth_percentiles(train_ds)
        lo = p1 / cfg.range_margin if lo is None else lo
        hi = p99 * cfg.range_margin if hi is None else hi
    alpha, beta = alpha_beta_from_range(lo, hi)
    return replace(model, alpha=alpha, beta=beta)


def pool_depth(depth: torch.Tensor, valid: torch.Tensor, size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Valid-aware area downsampling of ``(B, 1, H, W)`` depth: mean of the valid pixels of each cell."""
    v = valid.float()
    num = F.adaptive_avg_pool2d(depth.float() * v, size)
    den = F.adaptive_avg_pool2d(v, size)
    ok = den > 0.5  # a cell counts when most of it is valid, so edge cells do not blend fore- and background
    return torch.where(ok, num / den.clamp_min(1e-6), torch.zeros_like(num)), ok


def depth_loss(pred: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor, cfg: DepthTrainConfig) -> torch.Tensor:
    """The configured per-pixel loss (+ gradient term) of one scale over valid pixels; 0 with a grad if none."""
    if cfg.loss == "mse":
        loss = masked_mse(pred, gt, valid)
    elif cfg.loss == "l1":
        loss = masked_l1(pred, gt, valid)
    else:
        loss = scale_invariant_log(pred, gt, valid, lam=cfg.silog_lambda)
    if cfg.grad_weight > 0:
        loss = loss + cfg.grad_weight * gradient_loss(pred, gt, valid)
    return loss


def depth_step(cfg: DepthTrainConfig) -> Callable:
    """The loop's step function: multi-scale masked depth loss, logging the finest scale's AbsRel."""

    def step(model: nn.Module, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        x = batch["image"]
        if cfg.mask_input:
            x = torch.cat([x, batch["fg"].to(x.dtype)], dim=1)
        preds = model(x, multiscale=True)
        gt, valid = batch["depth"], batch["valid"]
        total = preds[0].sum() * 0.0
        for w, p in zip(cfg.scale_weights, preds, strict=False):
            if p.shape[-2:] == gt.shape[-2:]:
                g, v = gt, valid
            else:
                g, v = pool_depth(gt, valid, tuple(p.shape[-2:]))
            total = total + w * depth_loss(p, g, v, cfg)
        with torch.no_grad():
            p0 = preds[0].float()
            absrel = ((p0 - gt).abs() / gt.clamp_min(1e-6))[valid].mean() if bool(valid.any()) else p0.sum() * 0
        return total, {"abs_rel": float(absrel)}

    return step


def train_depth(cfg: DepthTrainConfig, ds: Path, out: Path, *, split: str = "train", resume: bool = False,
                overwrite: bool = False, device: str = "cpu",
                progress: Callable[[int, int, dict[str, float]], None] | None = None) -> TrainResult:
    """Train a DispNet on the ``split`` frames of ``ds`` into the run folder ``out`` (see cadalign.train.loop)."""

    sel = select(ds, split)
    base = DepthDataset(sel.scene_dir, sel.ids)
    data = ScaledDataset(base, cfg.scale, with_fg=cfg.mask_input)
    model_cfg = resolve_model_config(cfg, data)
    torch.manual_seed(cfg.loop.seed)
    model = DispNet(model_cfg)
    identity = {"task": "depth", "classes": list(base.classes.names), "model": model_cfg,
                "scale": cfg.scale, "mask_input": cfg.mask_input}
    write_run_record(out, "depth", cfg, identity,
                     {"depth_range_m": [1 / (model_cfg.alpha + model_cfg.beta), 1 / model_cfg.beta],
                      "dataset": {"scene": str(sel.scene_dir), "split": split, "ids": list(sel.ids),
                                  "source": sel.source}, "images": read_prep(sel.scene_dir)}, resume=resume,
                     overwrite=overwrite)
    log.info("depth: %d %s frames of %s, head range %.3f-%.3f m", len(sel.ids), split, sel.scene_dir,
             1 / (model_cfg.alpha + model_cfg.beta), 1 / model_cfg.beta)
    return train_loop(model, depth_step(cfg), data, cfg.loop, out,
                      augment=(lambda b, g: augment_dense(b, g, cfg.augment)), resume=resume, device=device,
                      progress=progress, extra_state=identity)

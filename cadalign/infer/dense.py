"""Dense per-frame inference: class probabilities (ResUNet) and metric depth (DispNet) for a frame.

``load_dense_model(run)`` reads a run folder written by ``cadalign train seg|depth`` (or a ``.pt`` checkpoint
in it) and rebuilds the network from the model config saved in the checkpoint. Frames go in at their full
size; the network runs at the training scale and its logits/depth are upsampled (bilinear) back, so the
outputs align pixel for pixel with the input. Images are (H, W, 3) uint8 RGB or (3, H, W) float in [0, 1].
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from cadalign.errors import InputError, TrainingError
from cadalign.models.dispnet import DispNet, DispNetConfig
from cadalign.models.resunet import ResUNet, ResUNetConfig
from cadalign.train.checkpoint import LAST, load_checkpoint
from cadalign.train.data import resized_size


@dataclass(frozen=True)
class DenseModel:
    task: Literal["seg", "depth"]
    """Which network: segmentation or depth."""
    model: nn.Module
    """The network in eval mode on ``device``."""
    classes: tuple[str, ...]
    """Class names of the dataset it was trained on (index 0 background)."""
    scale: float
    """Image scale the network runs at."""
    mask_input: bool
    """Depth only: the network takes a foreground mask as a 4th channel."""
    device: torch.device
    """Where the network runs."""
    checkpoint: Path
    """The checkpoint file it was loaded from."""
    steps: int
    """Optimiser steps the checkpoint was trained for."""


def checkpoint_path(run: Path) -> Path:
    """``run`` itself if it is a file, else ``run/checkpoints/last.pt``."""
    run = Path(run)
    return run if run.is_file() else run / "checkpoints" / LAST


def load_dense_model(run: Path, *, task: str | None = None, classes: Sequence[str] | None = None,
                     device: str = "cpu") -> DenseModel:
    """Load a trained seg/depth network from a run folder or checkpoint.

    Raises:
        TrainingError: missing/unreadable checkpoint, another task than ``task``, or a class list other than
            ``classes`` (a model trained on another dataset's classes must not be applied silently).
    """

    path = checkpoint_path(run)
    ck = load_checkpoint(path, map_location="cpu")
    ident = ck.get("extra_state", {})
    have = ident.get("task")
    if have not in ("seg", "depth"):
        raise TrainingError(f"{path} is not a segmentation or depth checkpoint (task {have!r})")
    if task is not None and have != task:
        raise TrainingError(f"{path} is a '{have}' model, not '{task}'; use 'cadalign eval {have}' or another run")
    names = tuple(ident.get("classes", ()))
    if classes is not None and tuple(classes) != names:
        raise TrainingError(f"{path} was trained on classes {list(names)}, the data has {list(classes)}; "
                            "evaluate on a dataset with the same class list or retrain")
    if have == "seg":
        model: nn.Module = ResUNet(len(names), ResUNetConfig(**ident["model"]))
    else:
        model = DispNet(DispNetConfig(**ident["model"]))
    model.load_state_dict(ck["model"])
    dev = torch.device(device)
    model.to(dev).eval()
    if have == "seg":  # channels-last: see _seg_probs
        model.to(memory_format=torch.channels_last)
    return DenseModel(have, model, names, float(ident.get("scale", 1.0)), bool(ident.get("mask_input", False)),
                      dev, path, int(ck.get("step", 0)))


def _as_batch(images: np.ndarray | torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) float in [0, 1] from one image or a batch, uint8 HWC or float CHW."""
    x = torch.as_tensor(images)
    if x.dtype == torch.uint8:
        x = x.float() / 255.0
        x = x.permute(2, 0, 1) if x.ndim == 3 else x.permute(0, 3, 1, 2)
    x = x.float()
    if x.ndim == 3:
        x = x[None]
    if x.ndim != 4 or x.shape[1] != 3:
        raise InputError(f"expected an (H, W, 3) uint8 or (3, H, W) float image (or a batch), got {tuple(x.shape)}")
    return x


def _run_scaled(dm: DenseModel, x: torch.Tensor) -> tuple[torch.Tensor, tuple[int, int]]:
    h, w = x.shape[-2:]
    size = resized_size(h, w, dm.scale)
    if size != (h, w):
        x = F.interpolate(x, size=size, mode="bilinear", antialias=True, align_corners=False)
    return x.to(dm.device), (h, w)


@torch.no_grad()
def seg_probabilities(dm: DenseModel, images: np.ndarray | torch.Tensor, *, flip_tta: bool = False) -> torch.Tensor:
    """Class probabilities ``(B, C, H, W)`` float32 (CPU) of one image or a batch at the input resolution.

    ``flip_tta``: also run the horizontally mirrored image and average the two probability maps (the mirrored
    one mirrored back); twice the network time. The trainers flip horizontally, never vertically, so the
    mirrored frame is an in-distribution view.
    """
    if dm.task != "seg":
        raise InputError(f"{dm.checkpoint} is a depth model; class probabilities need a segmentation model")
    x, (h, w) = _run_scaled(dm, _as_batch(images))
    prob = _seg_probs(dm, x, (h, w))
    if flip_tta:
        prob = 0.5 * (prob + _seg_probs(dm, x.flip(-1), (h, w)).flip(-1))
    return prob.cpu()


# The ResUNet runs in channels-last memory order: its narrow convolutions (12-192 channels in the 'fast' preset)
# took 0.73-0.75x the CPU time of NCHW on 640x480 frames (one thread, docs/tuning/demo_time.md), as oneDNN then
# needs no layout reorder around each layer. Probabilities differ from NCHW by < 1e-6 (summation order).
def _seg_probs(dm: DenseModel, x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    logits = dm.model(x.contiguous(memory_format=torch.channels_last)).float().contiguous()
    if logits.shape[-2:] != size:
        logits = F.interpolate(logits, size=size, mode="bilinear", align_corners=False)
    return logits.softmax(1)


@torch.no_grad()
def metric_depth(dm: DenseModel, images: np.ndarray | torch.Tensor,
                 fg_mask: np.ndarray | torch.Tensor | None = None) -> torch.Tensor:
    """Depth ``(B, H, W)`` metres float32 (CPU) of one image or a batch at the input resolution.

    Args:
        fg_mask: (H, W) or (B, H, W) foreground mask (e.g. predicted class != background); required when the
            model was trained with ``mask_input``, ignored otherwise.
    """
    if dm.task != "depth":
        raise InputError(f"{dm.checkpoint} is a segmentation model; metric depth needs a depth model")
    x = _as_batch(images)
    if dm.mask_input:
        if fg_mask is None:
            raise InputError(f"{dm.checkpoint} was trained with a mask input: pass fg_mask (class != background)")
        m = torch.as_tensor(fg_mask).float()
        m = m.reshape(-1, 1, *x.shape[-2:]).expand(x.shape[0], 1, *x.shape[-2:])
        x = torch.cat([x, m], dim=1)
    h, w = x.shape[-2:]
    size = resized_size(h, w, dm.scale)
    if size != (h, w):
        rgb = F.interpolate(x[:, :3], size=size, mode="bilinear", antialias=True, align_corners=False)
        x = torch.cat([rgb, F.interpolate(x[:, 3:], size=size, mode="nearest")], 1) if dm.mask_input else rgb
    depth = dm.model(x.to(dm.device)).float()
    if depth.shape[-2:] != (h, w):
        depth = F.interpolate(depth, size=(h, w), mode="bilinear", align_corners=False)
    return depth[:, 0].cpu()

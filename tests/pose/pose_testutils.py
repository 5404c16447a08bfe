"""Shared helpers of the detector + pose tests (a module, not conftest, so imports are unambiguous)."""

from __future__ import annotations

import numpy as np
import torch

from cadalign.cad.symmetry import Symmetry
from cadalign.models.maskrcnn import MaskRCNNConfig
from cadalign.train.pose_losses import ObjectGeometry, PoseLoss, PoseLossConfig


def tiny_cfg(**kw: object) -> MaskRCNNConfig:
    """A narrow ResNet-18 Mask R-CNN for 64x48 images (runs a step in ~50 ms on one thread)."""
    base = dict(width=8, fpn_channels=16, input_hw=(48, 64), anchor_sizes=(8.0, 16.0, 32.0, 64.0, 128.0),
                rpn_pre_nms_train=200, rpn_post_nms_train=100, rpn_pre_nms_test=100, rpn_post_nms_test=50,
                roi_batch_per_image=32, box_rep=32, mask_channels=16, pose_channels=16, pose_rep=32)
    base.update(kw)
    return MaskRCNNConfig(**base)  # type: ignore[arg-type]


TINY_K = torch.tensor([[60.0, 0, 32], [0, 60, 24], [0, 0, 1]])


def tiny_scene(seed: int) -> tuple[torch.Tensor, dict]:
    """A 64x48 image with a red square and a blue bar on a textured background, and their targets."""
    g = torch.Generator().manual_seed(seed)
    img = 0.3 + 0.1 * torch.rand(3, 48, 64, generator=g)
    masks = torch.zeros(2, 48, 64, dtype=torch.bool)
    masks[0, 8:24, 10:26] = True
    masks[1, 28:40, 30:58] = True
    img[:, masks[0]] = torch.tensor([0.9, 0.1, 0.1])[:, None]
    img[:, masks[1]] = torch.tensor([0.1, 0.2, 0.9])[:, None]
    target = {"boxes": torch.tensor([[10.0, 8, 26, 24], [30, 28, 58, 40]]), "labels": torch.tensor([1, 2]),
              "masks": masks, "R": torch.eye(3).expand(2, 3, 3).clone(), "t": torch.tensor([[-0.5, -0.3, 2.0],
                                                                                             [0.6, 0.4, 3.0]]),
              "K": TINY_K, "obj_ids": torch.tensor([1, 2])}
    return img, target


def tiny_pose_loss() -> PoseLoss:
    pts = np.random.default_rng(0).uniform(-0.1, 0.1, (32, 3))
    return PoseLoss({i: ObjectGeometry(pts, 0.35, Symmetry.none()) for i in (1, 2)}, PoseLossConfig())

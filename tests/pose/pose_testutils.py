"""Shared helpers of the detector + pose tests (a module, not conftest, so imports are unambiguous)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from cadalign.cad.symmetry import Symmetry
from cadalign.models.maskrcnn import MaskRCNNConfig
from cadalign.train.datasets import DetectionPoseDataset
from cadalign.train.pose import _resize_item, load_object_geometry, locate_dataset
from cadalign.train.pose_crop import masks_to_boxes
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

def bop_items(pose_bop: Path) -> list[dict]:
    ds = locate_dataset(pose_bop)
    data = DetectionPoseDataset(ds.scene_dir, ds.splits["train"][:3])
    return [data[i] for i in range(len(data))]


def on_mask_fraction(item: dict, geometry: dict, g: int) -> float:
    """How well the instance's CAD points projected with its GT pose explain its visible mask, in [0, 1].

    The smaller of: the fraction of projected points (in the image, in front) on the dilated mask, and the
    fraction of mask pixels inside the projected points' box (a model collapsed to a point covers nothing).
    """
    pts = torch.tensor(geometry[int(item["obj_ids"][g])].points_m, dtype=torch.float32)
    cam = pts @ item["R"][g].T + item["t"][g]
    uvw = cam @ item["K"].T
    uv = uvw[:, :2] / uvw[:, 2:]
    m = item["masks"][g]
    h, w = m.shape
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h) & (cam[:, 2] > 0)
    if not bool(inside.any()):
        return 0.0
    x = uv[inside, 0].long().clamp(0, w - 1)
    y = uv[inside, 1].long().clamp(0, h - 1)
    # dilate the mask by 2 px: projected surface points can fall just outside the rasterised pixels
    dil = torch.nn.functional.max_pool2d(m[None, None].float(), 5, 1, 2)[0, 0] > 0
    on_mask = float(dil[y, x].float().mean())
    u0, v0 = uv[inside].min(0).values - 2
    u1, v1 = uv[inside].max(0).values + 2
    ys, xs = torch.nonzero(m, as_tuple=True)
    covered = float(((xs + 0.5 >= u0) & (xs + 0.5 <= u1) & (ys + 0.5 >= v0) & (ys + 0.5 <= v1)).float().mean())
    return min(on_mask, covered)


def well_visible(item: dict) -> list[int]:
    return [g for g in range(len(item["labels"])) if int(item["masks"][g].sum()) >= 30]


def doubled_frame(pose_bop: Path) -> tuple[dict, dict, dict, tuple[int, int]]:
    """(object geometry, the frame with the most well-visible instances, that frame resized to twice its size,
    its original (h, w))."""
    geometry = load_object_geometry(locate_dataset(pose_bop).models_dir, 300)
    item = max(bop_items(pose_bop), key=lambda it: len(well_visible(it)))
    h0, w0 = item["image"].shape[-2:]
    return geometry, item, _resize_item(item, (2 * h0, 2 * w0)), (h0, w0)


def block_target(masks: torch.Tensor, t: torch.Tensor, K: torch.Tensor) -> dict:
    n = len(masks)
    return {"masks": masks, "boxes": masks_to_boxes(masks), "labels": torch.ones(n, dtype=torch.int64),
            "obj_ids": torch.arange(n), "R": torch.eye(3).repeat(n, 1, 1), "t": t, "K": K}

"""Shared helpers of the detector + pose tests (a module, not conftest, so imports are unambiguous)."""

from __future__ import annotations

from cadalign.models.maskrcnn import MaskRCNNConfig


def tiny_cfg(**kw: object) -> MaskRCNNConfig:
    """A narrow ResNet-18 Mask R-CNN for 64x48 images (runs a step in ~50 ms on one thread)."""
    base = dict(width=8, fpn_channels=16, input_hw=(48, 64), anchor_sizes=(8.0, 16.0, 32.0, 64.0, 128.0),
                rpn_pre_nms_train=200, rpn_post_nms_train=100, rpn_pre_nms_test=100, rpn_post_nms_test=50,
                roi_batch_per_image=32, box_rep=32, mask_channels=16, pose_channels=16, pose_rep=32)
    base.update(kw)
    return MaskRCNNConfig(**base)  # type: ignore[arg-type]

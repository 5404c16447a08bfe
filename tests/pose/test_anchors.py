"""Anchors with several scales per level, the RPN's IoU thresholds, and the small-object matching they fix."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from pose_testutils import tiny_cfg

from cadalign.config import from_dict, to_dict
from cadalign.models.maskrcnn import MaskRCNNConfig, MaskRCNNPose
from cadalign.models.maskrcnn.anchors import grid_anchors
from cadalign.models.maskrcnn.rpn import BELOW, match
from cadalign.models.ops import box_iou


def test_grid_anchors_with_several_sizes_is_size_major():
    a = grid_anchors((1, 2), 4, [8.0, 16.0], [1.0, 4.0])
    assert a.shape == (2 * 2 * 2, 4)
    # first cell (centre 2, 2): size 8 ratio 1, size 8 ratio 4 (h = 16, w = 4), size 16 ratio 1, size 16 ratio 4
    expected = [[-2, -2, 6, 6], [0, -6, 4, 10], [-6, -6, 10, 10], [-2, -14, 6, 18]]
    assert torch.allclose(a[:4], torch.tensor(expected, dtype=torch.float32))
    assert torch.allclose(a[4:] - a[:4], torch.tensor([4.0, 0, 4, 0]))  # second cell: shifted by the stride
    assert torch.equal(grid_anchors((3, 5), 8, 8.0, [0.5, 1, 2]), grid_anchors((3, 5), 8, [8.0], [0.5, 1, 2]))


def test_more_scales_and_a_lower_threshold_give_small_boxes_positive_anchors():
    """A 13 x 10 px box on a stride-4 grid: no anchor reaches IoU 0.5 (let alone 0.7) with one size per level;
    several do with three sizes per octave."""
    gt = torch.tensor([[102.0, 50.0, 115.0, 60.0]])
    one = torch.cat([grid_anchors((60, 80), 4, 8.0, (0.5, 1, 2)), grid_anchors((30, 40), 8, 18.0, (0.5, 1, 2))])
    three = torch.cat([grid_anchors((60, 80), 4, [8.0 * 2 ** (k / 3) for k in range(3)], (0.5, 1, 2)),
                       grid_anchors((30, 40), 8, [18.0 * 2 ** (k / 3) for k in range(3)], (0.5, 1, 2))])
    m_one = match(box_iou(gt, one), 0.5, 0.3, allow_low_quality=False)
    m_three = match(box_iou(gt, three), 0.5, 0.3, allow_low_quality=False)
    assert int((m_one >= 0).sum()) == 0
    assert int((m_three >= 0).sum()) >= 3
    assert int((m_three == BELOW).sum()) > 0


def test_config_defaults_keep_old_checkpoints_and_validate():
    cfg = MaskRCNNConfig()
    assert cfg.anchor_scales == (1.0,) and cfg.rpn_fg_iou == 0.7 and cfg.rpn_bg_iou == 0.3
    old = to_dict(cfg)
    for key in ("anchor_scales", "rpn_fg_iou", "rpn_bg_iou"):
        old.pop(key)
    assert from_dict(MaskRCNNConfig, old) == cfg  # a checkpoint written before these fields existed
    with pytest.raises(ValueError, match="rpn_bg_iou"):
        MaskRCNNConfig(rpn_fg_iou=0.4, rpn_bg_iou=0.5)
    with pytest.raises(ValueError, match="anchor_scales"):
        MaskRCNNConfig(anchor_scales=())


def test_multi_scale_rpn_trains_and_infers():
    torch.manual_seed(0)
    model = MaskRCNNPose(tiny_cfg(anchor_scales=(1.0, 2 ** (1 / 3), 2 ** (2 / 3)), rpn_fg_iou=0.5), ("bg", "a"))
    assert model.rpn.cls.out_channels == 9 and model.rpn.box.out_channels == 36
    masks = torch.zeros(1, 48, 64, dtype=torch.bool)
    masks[0, 10:17, 20:30] = True
    target = {"boxes": torch.tensor([[20.0, 10, 30, 17]]), "labels": torch.tensor([1]), "masks": masks,
              "R": torch.eye(3)[None], "t": torch.tensor([[0.0, 0, 3]]), "K": torch.eye(3),
              "obj_ids": torch.tensor([1])}
    losses = model(torch.rand(1, 3, 48, 64), [target])
    assert np.isfinite([float(v.detach()) for v in losses.values()]).all() and float(losses["rpn_box"].detach()) > 0
    model.eval()
    out = model(torch.rand(1, 3, 48, 64))
    assert out[0]["boxes"].shape[1] == 4


def test_training_pose_configs_resolve():
    from pathlib import Path

    from cadalign.config import resolve
    from cadalign.train.pose import PRESETS, PoseTrainConfig

    files = sorted((Path(__file__).resolve().parents[2] / "training").glob("pose_*.toml"))
    assert len(files) >= 4
    for f in files:
        cfg = resolve(PoseTrainConfig, PRESETS, "fast", f)
        assert cfg.model.pose in ("thesis", "improved")
        if cfg.crop_hw is not None:
            assert cfg.crop_hw[0] <= cfg.model.input_hw[0] and cfg.crop_hw[1] <= cfg.model.input_hw[1]

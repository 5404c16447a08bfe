"""Rolled training frames (``PoseTrainConfig.rotate_prob``): the camera turned about its optical axis."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch
from pose_testutils import block_target, doubled_frame, on_mask_fraction, well_visible

from cadalign.config import from_dict
from cadalign.errors import ConfigError
from cadalign.train.augment import AugmentConfig
from cadalign.train.datasets import detection_collate
from cadalign.train.pose import PoseTrainConfig, make_augment, targets_from_batch
from cadalign.train.pose_crop import crop_batch, draw_roll, masks_to_boxes, roll_frame, roll_matrix


def _block_scene(K: torch.Tensor, t: torch.Tensor, h: int = 60, w: int = 80) -> tuple[torch.Tensor, dict]:
    """A 3x3 bright block centred where ``K`` projects ``t`` (on a pixel centre), as image and mask."""
    u, v = (K @ t[0]).tolist()[:2]
    u, v = u / float(t[0, 2]), v / float(t[0, 2])
    x, y = int(math.floor(u)), int(math.floor(v))
    assert (u, v) == pytest.approx((x + 0.5, y + 0.5))
    image = torch.zeros(3, h, w)
    image[:, y - 1:y + 2, x - 1:x + 2] = 1.0
    return image, block_target(image[:1] > 0, t, K)


@pytest.mark.parametrize("deg", [25.0, -40.0, 90.0])
def test_roll_moves_projected_points_with_the_image(deg: float):
    """With fx != fy and an off-centre principal point the block still lands where ``K Rz t`` projects."""
    K = torch.tensor([[50.0, 0, 36], [0, 60, 28], [0, 0, 1]])
    t = torch.tensor([[0.22, 0.15, 2.0]])  # projects to (41.5, 32.5)
    image, target = _block_scene(K, t)
    theta = math.radians(deg)
    rolled, out = roll_frame(image, target, theta)
    assert torch.allclose(out["t"], t @ roll_matrix(theta).T) and float(out["t"][0, 2]) == pytest.approx(2.0)
    assert torch.allclose(out["R"][0], roll_matrix(theta), atol=1e-6) and torch.equal(out["K"], K)
    pu, pv = ((K @ out["t"][0]) / out["t"][0, 2]).tolist()[:2]
    img = rolled[0]
    ys, xs = torch.meshgrid(torch.arange(60) + 0.5, torch.arange(80) + 0.5, indexing="ij")
    cu, cv = float((img * xs).sum() / img.sum()), float((img * ys).sum() / img.sum())
    assert abs(cu - pu) < 0.15 and abs(cv - pv) < 0.15
    box = out["boxes"][0]
    assert float(box[0]) <= pu <= float(box[2]) and float(box[1]) <= pv <= float(box[3])
    assert torch.equal(box, masks_to_boxes(out["masks"])[0])
    # the block is not where the unrolled pose projects it (the test could fail)
    qu, qv = ((K @ t[0]) / t[0, 2]).tolist()[:2]
    assert math.hypot(cu - qu, cv - qv) > 2.0


def test_roll_by_zero_is_the_identity_and_drops_instances_rolled_out():
    K = torch.tensor([[50.0, 0, 40], [0, 50, 30], [0, 0, 1]])
    image, target = _block_scene(K, torch.tensor([[0.22, 0.1, 2.0]]))
    same, out = roll_frame(image, target, 0.0)
    assert torch.allclose(same, image, atol=1e-5) and torch.equal(out["masks"], target["masks"])
    # a block near the corner leaves the frame under a half turn about an off-centre principal point
    K2 = torch.tensor([[50.0, 0, 10], [0, 50, 8], [0, 0, 1]])
    corner_img, corner = _block_scene(K2, torch.tensor([[1.22, 0.82, 2.0]]))
    _, gone = roll_frame(corner_img, corner, math.pi)
    assert len(gone["masks"]) == 0 and gone["R"].shape == (0, 3, 3) and gone["boxes"].shape == (0, 4)


def test_rolled_crops_keep_masks_boxes_and_poses_consistent(pose_bop: Path):
    geometry, _, up, (h0, w0) = doubled_frame(pose_bop)
    batch = detection_collate([up])
    checked, worse = 0, 0
    for seed in range(6):
        out = crop_batch(batch, torch.Generator().manual_seed(seed), (h0, w0), object_prob=1.0, rotate_prob=1.0,
                         rotate_max_deg=45.0)
        tgt = targets_from_batch(out)[0]
        assert torch.equal(masks_to_boxes(tgt["masks"]), tgt["boxes"])
        assert torch.allclose(tgt["R"] @ tgt["R"].transpose(1, 2), torch.eye(3).expand(len(tgt["R"]), 3, 3),
                              atol=1e-5)
        for gi in well_visible(tgt):
            assert on_mask_fraction(tgt, geometry, gi) > 0.5
            # the pose before the roll misses the rolled mask unless the roll was small
            obj = int(tgt["obj_ids"][gi])
            src = int(torch.nonzero(up["obj_ids"] == obj)[0])
            unrolled = {**tgt, "R": up["R"][src][None].expand_as(tgt["R"]).clone(),
                        "t": up["t"][src][None].expand_as(tgt["t"]).clone()}
            worse += on_mask_fraction(unrolled, geometry, gi) < 0.5
            checked += 1
    assert checked >= 3 and worse >= 1


def test_roll_draws_and_config():
    g = torch.Generator().manual_seed(0)
    assert draw_roll(g, 0.0, 30.0) == 0.0 and torch.equal(g.get_state(), torch.Generator().manual_seed(0).get_state())
    rolls = [math.degrees(draw_roll(g, 1.0, 30.0)) for _ in range(200)]
    assert -30.0 <= min(rolls) < -25.0 and 25.0 < max(rolls) <= 30.0
    assert make_augment(AugmentConfig(enabled=False), rotate_prob=0.5, input_hw=(48, 64)) is not None
    with pytest.raises(ValueError, match="input_hw"):
        make_augment(AugmentConfig(enabled=False), rotate_prob=0.5)
    assert PoseTrainConfig(rotate_prob=0.5).rotate_max_deg == 30.0
    assert from_dict(PoseTrainConfig, {"rotate_prob": 0.5, "rotate_max_deg": 45.0}).rotate_max_deg == 45.0
    with pytest.raises(ConfigError, match="rotate_max_deg"):
        from_dict(PoseTrainConfig, {"rotate_max_deg": 200.0})


def test_label_map_and_per_mask_rolls_agree():
    """Disjoint masks go through one label map (nearest), overlapping ones mask by mask (bilinear): same boxes
    rule, and on a block the two agree to a pixel."""
    K = torch.tensor([[50.0, 0, 40], [0, 55, 30], [0, 0, 1]])
    masks = torch.zeros(3, 60, 80, dtype=torch.bool)
    masks[0, 10:20, 12:30] = True
    masks[1, 35:50, 50:60] = True
    masks[2, 22:26, 5:9] = True
    t = torch.tensor([[0.1, 0.0, 2.0], [0.2, 0.1, 3.0], [-0.3, 0.0, 2.5]])
    image = masks.any(0).float()[None].repeat(3, 1, 1)
    _, disjoint = roll_frame(image, block_target(masks, t, K), math.radians(20))
    assert torch.equal(disjoint["boxes"], masks_to_boxes(disjoint["masks"]))
    overlapping = masks.clone()
    overlapping[2, 12:16, 14:18] = True  # now overlaps mask 0
    _, each = roll_frame(image, block_target(overlapping, t, K), math.radians(20))
    assert torch.equal(each["boxes"], masks_to_boxes(each["masks"]))
    assert (each["boxes"][:2] - disjoint["boxes"][:2]).abs().max() <= 1.0
    assert (each["masks"][:2] ^ disjoint["masks"][:2]).sum() < 0.1 * disjoint["masks"][:2].sum()

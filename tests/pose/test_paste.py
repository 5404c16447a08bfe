"""Pasted training frames (``PoseTrainConfig.paste_prob``): instances of another frame copied in where they are."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from pose_testutils import block_target, bop_items, on_mask_fraction, well_visible

from cadalign.train.augment import AugmentConfig
from cadalign.train.datasets import detection_collate
from cadalign.train.loop import LoopConfig
from cadalign.train.pose import PoseTrainConfig, load_object_geometry, locate_dataset, make_augment, targets_from_batch
from cadalign.train.pose_crop import crop_batch, draw_paste, masks_to_boxes, paste_instances

K = torch.tensor([[50.0, 0, 40], [0, 50, 30], [0, 0, 1]])


def _frame(blocks: list[tuple[int, int, int, int]], value: float, z0: float) -> tuple[torch.Tensor, dict]:
    """An image of constant ``value`` and one instance per ``(y0, y1, x0, x1)`` block, at depths ``z0 + i``."""
    masks = torch.zeros(len(blocks), 60, 80, dtype=torch.bool)
    for i, (y0, y1, x0, x1) in enumerate(blocks):
        masks[i, y0:y1, x0:x1] = True
    t = torch.tensor([[0.1 * i, 0.0, z0 + i] for i in range(len(blocks))])
    return torch.full((3, 60, 80), value), block_target(masks, t, K.clone())


def test_paste_copies_pixels_and_poses_and_occludes_the_frame():
    image, target = _frame([(10, 20, 10, 30), (40, 44, 60, 64)], 0.2, 2.0)
    donor_image, donor = _frame([(8, 22, 5, 25), (38, 46, 58, 66), (0, 4, 0, 4)], 0.9, 5.0)
    donor["labels"] = torch.tensor([2, 3, 2])
    out_image, out = paste_instances(image, target, donor_image, donor, [0, 1])
    cover = donor["masks"][:2].any(0)
    assert torch.equal(out_image[:, cover], donor_image[:, cover])
    assert torch.equal(out_image[:, ~cover], image[:, ~cover])
    # the frame's first block keeps its 50 uncovered pixels (25 %); the second is covered whole and dropped
    assert len(out["labels"]) == 3 and out["labels"].tolist() == [1, 2, 3]
    assert int(out["masks"][0].sum()) == 50 and not bool((out["masks"][0] & cover).any())
    assert torch.equal(out["R"][1:], donor["R"][:2]) and torch.equal(out["t"][1:], donor["t"][:2])
    assert torch.equal(out["t"][0], target["t"][0]) and torch.equal(out["K"], K)
    assert torch.equal(out["boxes"], masks_to_boxes(out["masks"]))
    assert out["boxes"][0].tolist() == [25.0, 10.0, 30.0, 20.0]


def test_later_picks_cover_earlier_ones_and_mostly_covered_instances_go():
    image, target = _frame([(0, 10, 0, 10)], 0.2, 2.0)
    donor_image, donor = _frame([(30, 40, 30, 50), (30, 40, 40, 50), (30, 40, 30, 49)], 0.9, 5.0)
    _, out = paste_instances(image, target, donor_image, donor, [0, 1])
    assert len(out["labels"]) == 3  # the frame's block, donor 0 (half covered by donor 1), donor 1
    assert int(out["masks"][1].sum()) == 100 and int(out["masks"][2].sum()) == 100
    assert not bool((out["masks"][1] & out["masks"][2]).any())
    # donor 0 under donor 2 keeps one column of 10 pixels: 5 % of 200, under min_visible, so it is dropped
    _, out2 = paste_instances(image, target, donor_image, donor, [0, 2])
    assert len(out2["labels"]) == 2 and torch.equal(out2["t"][1], donor["t"][2])
    _, same = paste_instances(image, target, donor_image, donor, [])
    assert same is target


def test_paste_draws():
    image, target = _frame([(10, 20, 10, 30)], 0.2, 2.0)
    donor_image, donor = _frame([(0, 3, 0, 3)] * 9 + [(50, 53, 70, 73)], 0.9, 5.0)
    donor["labels"] = torch.tensor([1] * 9 + [2])
    g = torch.Generator().manual_seed(0)
    assert draw_paste(g, 0.0, 3, donor, image, target) == []
    assert torch.equal(g.get_state(), torch.Generator().manual_seed(0).get_state())  # nothing drawn
    draws = [draw_paste(g, 1.0, 1, donor, image, target) for _ in range(400)]
    rare = sum(d == [9] for d in draws) / len(draws)
    assert 0.4 < rare < 0.6  # class-balanced: the one class-2 instance half the time, not 1 in 10
    assert all(len(set(d)) == len(d) and 1 <= len(d) <= 3 for d in
               (draw_paste(g, 1.0, 3, donor, image, target) for _ in range(50)))
    half = [draw_paste(g, 0.5, 2, donor, image, target) for _ in range(400)]
    assert 0.4 < sum(d == [] for d in half) / len(half) < 0.6
    other_camera = {**donor, "K": K * torch.tensor([[1.1], [1.1], [1.0]])}
    assert draw_paste(g, 1.0, 3, other_camera, image, target) == []
    assert draw_paste(g, 1.0, 3, donor, image[:, :50], target) == []


def test_pasted_crops_keep_poses_consistent_with_pixels(pose_bop: Path):
    """Real simulated frames: every well-visible instance of a pasted frame, the pasted ones included, projects
    onto its mask with its pose; a pasted part given the frame's own pose of that part would not."""
    geometry = load_object_geometry(locate_dataset(pose_bop).models_dir, 300)
    frames = bop_items(pose_bop)[:2]
    h, w = frames[0]["image"].shape[-2:]
    batch = detection_collate(frames)
    pasted, wrong = 0, 0
    for seed in range(4):
        out = crop_batch(batch, torch.Generator().manual_seed(seed), (h, w), object_prob=1.0, paste_prob=1.0,
                         paste_max=3)
        for i, tgt in enumerate(targets_from_batch(out)):
            assert torch.equal(masks_to_boxes(tgt["masks"]), tgt["boxes"])
            own, donor = frames[i], frames[1 - i]
            for g in well_visible(tgt):
                assert on_mask_fraction(tgt, geometry, g) > 0.5
                from_donor = bool(((donor["t"] - tgt["t"][g]).abs().sum(1) < 1e-6).any())
                own_same = torch.nonzero(own["obj_ids"] == tgt["obj_ids"][g]).squeeze(1)
                if from_donor and len(own_same):
                    pasted += 1
                    j = int(own_same[0])
                    mixed = {**tgt, "R": own["R"][j][None].expand_as(tgt["R"]).clone(),
                             "t": own["t"][j][None].expand_as(tgt["t"]).clone()}
                    wrong += on_mask_fraction(mixed, geometry, g) < 0.5
    assert pasted >= 2 and wrong >= 1


def test_paste_config():
    assert make_augment(AugmentConfig(enabled=False), paste_prob=0.5, input_hw=(48, 64)) is not None
    with pytest.raises(ValueError, match="input_hw"):
        make_augment(AugmentConfig(enabled=False), paste_prob=0.5)
    with pytest.raises(ValueError, match="batch_size"):
        PoseTrainConfig(paste_prob=0.5, loop=LoopConfig(batch_size=1))
    assert PoseTrainConfig(paste_prob=0.5, loop=LoopConfig(batch_size=2)).paste_max == 3
    # a batch of one image pastes nothing and draws nothing
    image, target = _frame([(10, 20, 10, 30)], 0.2, 2.0)
    one = {"image": image[None], **{k: [v] for k, v in target.items()}}
    g = torch.Generator().manual_seed(1)
    out = crop_batch(one, g, (60, 80), paste_prob=1.0)
    assert torch.equal(out["image"], one["image"]) and len(out["labels"][0]) == 1

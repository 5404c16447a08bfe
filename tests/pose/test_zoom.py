"""Zoomed training crops (``PoseTrainConfig.zoom_prob``): image, masks, boxes, K and poses stay consistent."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from pose_testutils import block_target, doubled_frame, on_mask_fraction, well_visible

from cadalign.models.maskrcnn.pose_head import encode_translation
from cadalign.train.augment import AugmentConfig
from cadalign.train.datasets import detection_collate
from cadalign.train.pose import make_augment, targets_from_batch
from cadalign.train.pose_crop import crop_batch, draw_zoom, masks_to_boxes, zoom_target


def test_zoom_target_doubles_boxes_and_focal_length():
    masks = torch.zeros(1, 10, 12, dtype=torch.bool)
    masks[0, 2:5, 3:7] = True
    K = torch.tensor([[10.0, 0, 6], [0, 11, 5], [0, 0, 1]])
    out = zoom_target(block_target(masks, torch.tensor([[0.1, 0.2, 3.0]]), K), (20, 24))
    assert out["boxes"].tolist() == [[6.0, 4.0, 14.0, 10.0]]
    assert torch.allclose(out["K"], torch.tensor([[20.0, 0, 12], [0, 22, 10], [0, 0, 1]]))
    assert torch.equal(out["t"], torch.tensor([[0.1, 0.2, 3.0]]))


def test_zoom_moves_projected_points_with_the_image():
    """A bright 2x2 block painted where K projects a point stays under the point's projection with the zoomed K."""
    h, w = 48, 64
    K = torch.tensor([[50.0, 0, 32], [0, 50, 24], [0, 0, 1]])
    t = torch.tensor([[0.3, -0.1, 2.0]])
    u, v = (K @ t[0]).tolist()[:2]
    assert (u / 2.0, v / 2.0) == (39.5, 21.5)  # the centre of pixels 38..40 x 20..22 (pixel i covers [i, i + 1))
    image = torch.zeros(1, 3, h, w)
    image[0, :, 20:23, 38:41] = 1.0
    masks = image[0, :1] > 0
    batch = detection_collate([{"image": image[0], **block_target(masks, t, K)}])
    checked = 0
    for seed in range(12):
        out = crop_batch(batch, torch.Generator().manual_seed(seed), (24, 32), object_prob=1.0, zoom_prob=1.0,
                         zoom_max=2.0)
        img, Kz = out["image"][0, 0], out["K"][0]
        pu, pv = (Kz @ t[0]).tolist()[:2]
        if not (5 < pu / 2.0 < 27 and 5 < pv / 2.0 < 19):
            continue  # the block is cut by the crop's border: its centroid moves
        checked += 1
        ys, xs = torch.meshgrid(torch.arange(24) + 0.5, torch.arange(32) + 0.5, indexing="ij")
        cu, cv = float((img * xs).sum() / img.sum()), float((img * ys).sum() / img.sum())
        assert abs(cu - pu / 2.0) < 0.15 and abs(cv - pv / 2.0) < 0.15  # centroid (bilinear sampling: ~0.06 px)
        box = out["boxes"][0][0]
        assert float(box[0]) <= pu / 2.0 <= float(box[2]) and float(box[1]) <= pv / 2.0 <= float(box[3])
    assert checked >= 4


def test_zoomed_crops_keep_masks_boxes_and_poses_consistent(pose_bop: Path):
    geometry, _, up, (h0, w0) = doubled_frame(pose_bop)
    batch = detection_collate([up])
    zooms, checked = set(), 0
    for seed in range(6):
        g = torch.Generator().manual_seed(seed)
        out = crop_batch(batch, g, (h0, w0), object_prob=1.0, zoom_prob=1.0, zoom_max=2.0)
        tgt = targets_from_batch(out)[0]
        assert out["image"].shape[-2:] == (h0, w0) and tgt["masks"].shape[-2:] == (h0, w0)
        assert torch.equal(masks_to_boxes(tgt["masks"]), tgt["boxes"])
        zooms.add(round(float(tgt["K"][0, 0] / up["K"][0, 0]), 2))
        assert torch.allclose(tgt["K"][0, 0] / up["K"][0, 0], tgt["K"][1, 1] / up["K"][1, 1], rtol=0.05)
        for gi in well_visible(tgt):
            assert on_mask_fraction(tgt, geometry, gi) > 0.5
            checked += 1
        # the improved head's depth code (object extent) does not depend on the zoom
        if len(tgt["t"]):
            code = encode_translation(tgt["t"], tgt["K"].expand(len(tgt["t"]), 3, 3), tgt["boxes"])
            assert bool((code[:, 2] > 0).all())
    assert checked >= 3 and len(zooms) >= 3 and max(zooms) > 1.2


def test_zoom_draws_and_config():
    g = torch.Generator().manual_seed(0)
    assert draw_zoom(g, 0.0, 2.0) == 1.0 and torch.equal(g.get_state(), torch.Generator().manual_seed(0).get_state())
    z = [draw_zoom(g, 1.0, 2.0) for _ in range(200)]
    assert 1.0 <= min(z) and max(z) <= 2.0 and max(z) > 1.8
    assert make_augment(AugmentConfig(enabled=False), zoom_prob=0.5, input_hw=(48, 64)) is not None
    with pytest.raises(ValueError, match="input_hw"):
        make_augment(AugmentConfig(enabled=False), zoom_prob=0.5)


def test_class_balanced_crop_centres():
    """Nine valves and one hot stab: uniform over instances centres the hot stab in ~1 of 10 crops, class-balanced
    in ~1 of 2; the same random numbers are drawn either way, so the stream after a crop does not change."""
    from cadalign.train.pose_crop import crop_origin

    hw, crop = (200, 400), (20, 20)
    valves = torch.tensor([[10.0 + 20 * i, 10, 14 + 20 * i, 14] for i in range(9)])
    boxes = torch.cat([valves, torch.tensor([[380.0, 180, 386, 186]])])
    labels = torch.tensor([1] * 9 + [2])

    def hot_stab_share(balanced: bool) -> float:
        g = torch.Generator().manual_seed(0)
        hits = 0
        for _ in range(400):
            y0, x0 = crop_origin(hw, crop, boxes, g, 1.0, labels if balanced else None)
            hits += (x0 <= 383 < x0 + crop[1]) and (y0 <= 183 < y0 + crop[0])
        return hits / 400

    assert 0.05 < hot_stab_share(False) < 0.16
    assert 0.42 < hot_stab_share(True) < 0.58
    g1, g2 = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    crop_origin(hw, crop, boxes, g1, 1.0)
    crop_origin(hw, crop, boxes, g2, 1.0, labels)
    assert torch.equal(torch.rand(3, generator=g1), torch.rand(3, generator=g2))
    # one class present: the balanced draw is the uniform one
    assert [crop_origin(hw, crop, valves, torch.Generator().manual_seed(s), 1.0, labels[:9]) for s in range(20)] == \
        [crop_origin(hw, crop, valves, torch.Generator().manual_seed(s), 1.0) for s in range(20)]

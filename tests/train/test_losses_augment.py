"""Losses (exact values, empty masks) and augmentations (targets follow the image, depth rescaled by crops)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.train.augment import AugmentConfig, augment_dense, colour_jitter
from cadalign.train.depth import DepthTrainConfig, depth_loss, pool_depth
from cadalign.train.losses import (
    IGNORE,
    cross_entropy,
    gradient_loss,
    masked_l1,
    masked_mse,
    median_frequency_weights,
    scale_invariant_log,
    soft_dice,
)


def test_masked_losses_by_hand():
    pred = torch.tensor([[[[1.0, 2.0], [4.0, 9.0]]]])
    gt = torch.tensor([[[[2.0, 2.0], [2.0, 0.0]]]])
    valid = gt > 0
    assert float(masked_mse(pred, gt, valid)) == pytest.approx((1 + 0 + 4) / 3)
    assert float(masked_l1(pred, gt, valid)) == pytest.approx((1 + 0 + 2) / 3)
    d = np.log([0.5, 1.0, 2.0])
    assert float(scale_invariant_log(pred, gt, valid, lam=0.0)) == pytest.approx(math.sqrt((d**2).mean()), abs=1e-5)
    # fully scale invariant: a global factor costs nothing
    assert float(scale_invariant_log(gt * 3 + (gt == 0), gt, valid, lam=1.0)) == pytest.approx(0.0, abs=2e-3)


def test_gradient_loss_ignores_offsets_in_log_space_and_counts_valid_pairs():
    gt = torch.rand(1, 1, 6, 7) + 1
    assert float(gradient_loss(gt * 2.5, gt, gt > 0)) == pytest.approx(0.0, abs=1e-5)
    pred = gt.clone()
    pred[..., 3, 3] *= 2
    assert float(gradient_loss(pred, gt, gt > 0)) > 0


@pytest.mark.parametrize("fn", [masked_mse, masked_l1, scale_invariant_log, gradient_loss])
def test_depth_losses_empty_mask_zero_with_grad(fn):
    pred = torch.rand(2, 1, 4, 5, requires_grad=True)
    loss = fn(pred, torch.zeros(2, 1, 4, 5), torch.zeros(2, 1, 4, 5, dtype=torch.bool))
    loss.backward()
    assert float(loss.detach()) == 0.0 and torch.isfinite(pred.grad).all() and float(pred.grad.abs().sum()) == 0.0


def test_seg_losses_empty_and_perfect():
    logits = torch.randn(1, 3, 4, 4, requires_grad=True)
    none = torch.full((1, 4, 4), IGNORE)
    for loss in (cross_entropy(logits, none), soft_dice(logits, none)):
        loss.backward()
        assert float(loss.detach()) == 0.0 and torch.isfinite(logits.grad).all()
    label = torch.randint(0, 3, (1, 4, 4))
    perfect = torch.nn.functional.one_hot(label, 3).permute(0, 3, 1, 2).float() * 50
    assert float(cross_entropy(perfect, label)) == pytest.approx(0.0, abs=1e-6)
    assert float(soft_dice(perfect, label)) == pytest.approx(0.0, abs=1e-6)
    assert float(soft_dice(-perfect, label)) > 0.9


def test_median_frequency_weights_by_hand():
    w = median_frequency_weights(np.array([900, 80, 20, 0]), np.array([1000, 1000, 500, 0]))
    # frequencies 0.9, 0.08, 0.04 -> median 0.08
    assert w.tolist() == pytest.approx([0.08 / 0.9, 1.0, 2.0, 0.0])


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**16), st.floats(0.0, 1.0), st.sampled_from(["mse", "l1", "silog"]))
def test_depth_loss_finite_for_any_mask(seed, frac, kind):
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(2, 1, 8, 6, generator=g) * 10
    valid = torch.rand(2, 1, 8, 6, generator=g) < frac
    gt = torch.where(valid, gt + 0.01, torch.zeros_like(gt))
    pred = (torch.rand(2, 1, 8, 6, generator=g) * 10 + 0.1).requires_grad_()
    loss = depth_loss(pred, gt, valid, DepthTrainConfig(loss=kind, grad_weight=0.5))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(pred.grad).all()


def test_pool_depth_averages_valid_pixels_only():
    d = torch.tensor([[[[2.0, 4.0], [0.0, 6.0]]]])
    pooled, ok = pool_depth(d, d > 0, (1, 1))
    assert float(pooled) == pytest.approx(4.0) and bool(ok)
    pooled, ok = pool_depth(d, torch.zeros_like(d, dtype=torch.bool), (1, 1))
    assert float(pooled) == 0.0 and not bool(ok)


def _batch() -> dict:
    x = torch.linspace(0, 1, 16).repeat(12, 1)  # brightness encodes the column
    image = torch.stack([x, x.flip(0), torch.zeros_like(x)])[None].repeat(3, 1, 1, 1)
    label = (x > 0.5).long()[None].repeat(3, 1, 1)
    depth = torch.full((3, 1, 12, 16), 2.0)
    depth[:, :, :, :3] = 0
    return {"image": image, "label": label, "depth": depth, "valid": depth > 0, "im_id": torch.arange(3)}


def test_flip_and_crop_move_targets_with_the_image():
    cfg = AugmentConfig(hflip=1.0, crop_prob=1.0, crop_min=0.6, brightness=0, contrast=0, saturation=0, hue=0,
                        turbidity=0, noise=0)
    out = augment_dense(_batch(), torch.Generator().manual_seed(1), cfg)
    for i in range(3):
        # the label is still "column brightness > 0.5" of the augmented image (flipped: the right half became left)
        img_col = out["image"][i, 0]
        lab = out["label"][i]
        assert ((img_col > 0.55) <= (lab == 1)).all() and ((img_col < 0.45) <= (lab == 0)).all()
        assert bool((lab[:, 0] == 1).all())  # flipped: the bright side is now on the left
        s = set(out["depth"][i][out["valid"][i]].unique().tolist())
        assert len(s) == 1 and 2.0 * 0.6 - 1e-6 <= s.pop() <= 2.0 + 1e-6  # depth scaled by the crop side
        assert bool((out["valid"][i] == (out["depth"][i] > 0)).all())
    off = augment_dense(_batch(), torch.Generator(), AugmentConfig(enabled=False))
    assert torch.equal(_batch()["label"], off["label"]) and torch.equal(_batch()["image"], off["image"])


def test_augment_is_deterministic_per_generator_and_colour_in_range():
    a = augment_dense(_batch(), torch.Generator().manual_seed(5), AugmentConfig())
    b = augment_dense(_batch(), torch.Generator().manual_seed(5), AugmentConfig())
    c = augment_dense(_batch(), torch.Generator().manual_seed(6), AugmentConfig())
    assert all(torch.equal(a[k], b[k]) for k in ("image", "label", "depth"))
    assert not torch.equal(a["image"], c["image"])
    jit = colour_jitter(torch.rand(4, 3, 8, 8), torch.Generator().manual_seed(0), AugmentConfig(turbidity=0.9))
    assert float(jit.min()) >= 0 and float(jit.max()) <= 1


def test_random_patches_focus_on_small_classes_and_keep_targets_aligned():
    from cadalign.train.augment import random_patches

    h, w = 40, 60
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    image = torch.stack([yy / h, xx / w, torch.zeros(h, w)]).float()[None].repeat(4, 1, 1, 1)
    label = torch.zeros(4, h, w, dtype=torch.long)
    label[:, 37, 55] = 3  # one pixel of a rare class in a corner
    depth = (yy * w + xx).float()[None, None].repeat(4, 1, 1, 1) + 1
    batch = {"image": image, "label": label, "depth": depth, "valid": depth > 0, "im_id": torch.arange(4)}
    out = random_patches(batch, torch.Generator().manual_seed(0), (16, 20), focus_prob=1.0)
    assert out["image"].shape == (4, 3, 16, 20) and out["label"].shape == (4, 16, 20)
    assert bool((out["label"] == 3).flatten(1).any(1).all())  # every patch holds the rare pixel
    # all keys come from the same window: depth encodes the pixel index, the image its coordinates
    idx = out["depth"][:, 0] - 1
    assert torch.allclose(out["image"][:, 0] * h, torch.div(idx, w, rounding_mode="floor"))
    assert torch.allclose(out["image"][:, 1] * w, idx % w)
    uniform = random_patches(batch, torch.Generator().manual_seed(0), (16, 20), focus_prob=0.0)
    assert not bool((uniform["label"] == 3).flatten(1).any(1).all())
    assert random_patches(batch, torch.Generator(), (80, 80))["image"].shape == (4, 3, h, w)



def test_focal_cross_entropy_by_hand():
    logits = torch.tensor([[[[0.0, 1.0]], [[0.0, 0.0]]]])  # (1, 2, 1, 2): p_true of class 0 = 0.5 and e/(e+1)
    p = torch.tensor([0.5, math.e / (math.e + 1)])
    want = float(((1 - p) ** 2 * -torch.log(p)).mean())
    label = torch.tensor([[[0, 0]]])
    assert float(cross_entropy(logits, label, gamma=2.0)) == pytest.approx(want, rel=1e-5)
    w = torch.tensor([3.0, 1.0])
    assert float(cross_entropy(logits, label, w, gamma=2.0)) == pytest.approx(want, rel=1e-5)  # one class: w cancels
    mixed = torch.tensor([[[0, 1]]])
    p2, lw = torch.tensor([0.5, 1 / (math.e + 1)]), torch.tensor([3.0, 1.0])
    want2 = float((lw * (1 - p2) ** 2 * -torch.log(p2)).sum() / lw.sum())
    assert float(cross_entropy(logits, mixed, w, gamma=2.0)) == pytest.approx(want2, rel=1e-5)
    ignored = torch.tensor([[[0, IGNORE]]])
    assert float(cross_entropy(logits, ignored, w, gamma=2.0)) == pytest.approx(0.25 * math.log(2), rel=1e-5)


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 1000))
def test_focal_gamma_zero_is_weighted_ce_and_gamma_lowers_it(seed):
    g = torch.Generator().manual_seed(seed)
    x, y = torch.randn(2, 4, 5, 6, generator=g), torch.randint(0, 4, (2, 5, 6), generator=g)
    y[0, 0, 0] = IGNORE
    w = torch.rand(4, generator=g) + 0.5
    ref = torch.nn.functional.cross_entropy(x, y, weight=w, ignore_index=IGNORE)
    assert float(cross_entropy(x, y, w, gamma=0.0)) == pytest.approx(float(ref), rel=1e-6)
    assert float(cross_entropy(x, y, w, gamma=2.0)) < float(ref)


def test_focus_weights_pick_the_weighted_class():
    from cadalign.train.augment import random_patches

    h, w = 40, 60
    label = torch.zeros(6, h, w, dtype=torch.long)
    label[:, :, :10] = 1  # a big class on the left
    label[:, 37, 55] = 3  # one pixel of a rare class in the right corner
    batch = {"image": torch.rand(6, 3, h, w), "label": label}
    rare = random_patches(batch, torch.Generator().manual_seed(0), (16, 20), 1.0, focus_weights=[0, 0, 5, 1])
    assert bool((rare["label"] == 3).flatten(1).any(1).all())  # class 2 is absent: only class 3 can be drawn
    big = random_patches(batch, torch.Generator().manual_seed(0), (16, 20), 1.0, focus_weights=[0, 1, 0, 0])
    assert not bool((big["label"] == 3).any()) and bool((big["label"] == 1).flatten(1).any(1).all())
    zero = random_patches(batch, torch.Generator().manual_seed(0), (16, 20), 1.0, focus_weights=[0, 0, 0, 0])
    assert torch.equal(zero["label"], random_patches(batch, torch.Generator().manual_seed(0), (16, 20), 1.0)["label"])


def test_seg_class_and_focus_weights_by_hand():
    from cadalign.train.seg import SegTrainConfig, class_weights, focus_weights

    counts, image_counts = np.array([600, 300, 96, 4, 0]), np.array([1000, 1000, 1000, 1000, 0])
    # frequencies 0.6, 0.3, 0.096, 0.004 -> median 0.198; weights 0.33, 0.66, 2.06, 49.5
    full = class_weights(counts, image_counts, SegTrainConfig(max_class_weight=100.0))
    assert full == pytest.approx([0.198 / 0.6, 0.198 / 0.3, 0.198 / 0.096, 0.198 / 0.004, 0.0])
    root = class_weights(counts, image_counts, SegTrainConfig(max_class_weight=5.0, class_weight_power=0.5))
    assert root == pytest.approx([max(math.sqrt(0.33), 0.2), math.sqrt(0.66), math.sqrt(0.198 / 0.096), 5.0, 0.0])
    assert class_weights(counts, image_counts, SegTrainConfig(class_weighting="none")) is None
    # shares 0.6, 0.3, 0.096, 0.004: below 1 % only class 3 is rare and gets its own cap; the absent class stays 0
    rare = class_weights(counts, image_counts, SegTrainConfig(max_class_weight=2.0, rare_class_share=0.01,
                                                              max_rare_class_weight=4.0))
    assert rare == pytest.approx([0.5, 0.66, 2.0, 4.0, 0.0], abs=0.01)
    assert class_weights(counts, image_counts, SegTrainConfig(max_class_weight=2.0, rare_class_share=0.1,
                                                              max_rare_class_weight=4.0)) == pytest.approx(
        [0.5, 0.66, 0.198 / 0.096, 4.0, 0.0], abs=0.01)  # class 2 (9.6 %) now rare too: its 2.06 is under 4
    assert focus_weights(counts, SegTrainConfig()) is None
    assert focus_weights(counts, SegTrainConfig(focus_power=0.5)) == pytest.approx(
        [600**-0.5, 300**-0.5, 96**-0.5, 0.5, 0.0])


def test_fast_seg_preset_weighs_hot_stabs_above_valves_and_the_s10_recipe_did_not(repo_root):
    """On the default scene's training pixel counts (83 frames: hot stabs 0.04 %, valves 0.8 %) the fast preset
    caps the hot stab at 4 and the valve at 2; training/seg_fast_s10.toml restores the former common cap of 2."""
    from cadalign.config import resolve
    from cadalign.train.seg import PRESETS, SegTrainConfig, class_weights

    counts = np.array([16946623, 8341309, 198993, 10675])
    image_counts = np.full(4, 25497600)
    fast = resolve(SegTrainConfig, PRESETS, "fast")
    assert class_weights(counts, image_counts, fast) == pytest.approx([0.502, 0.715, 2.0, 4.0], abs=1e-3)
    s10 = resolve(SegTrainConfig, PRESETS, "fast", repo_root / "training" / "seg_fast_s10.toml")
    assert class_weights(counts, image_counts, s10) == pytest.approx([0.502, 0.715, 2.0, 2.0], abs=1e-3)
    assert (s10.focus_prob, s10.focus_power) == (0.7, 0.5) and (fast.focus_prob, fast.focus_power) == (0.8, 1.0)

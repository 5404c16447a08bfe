"""Boundary-weighted cross-entropy, the channels-last layout and the whole-frame final phase of the seg trainer."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.train.losses import IGNORE, boundary_weights, cross_entropy


def test_boundary_weights_by_hand():
    lab = torch.tensor([[[0, 0, 0, 0, 0],
                         [0, 0, 0, 0, 0],
                         [0, 0, 0, 0, 2],
                         [1, 1, 1, IGNORE, 2]]])
    w = boundary_weights(lab, 2.0)
    want = torch.tensor([[[1, 1, 1, 1, 1],
                          [1, 1, 1, 3, 3],
                          [3, 3, 3, 3, 3],
                          [3, 3, 3, 1, 3]]], dtype=torch.float32)
    assert torch.equal(w, want)  # the ignored pixel is neither boosted nor a neighbour of another class
    wide = boundary_weights(lab, 1.0, radius=2)
    assert float(wide[0, 0, 3]) == 2.0 and float(wide[0, 0, 0]) == 1.0


def test_one_pixel_bar_is_boosted_all_along():
    lab = torch.zeros(1, 7, 9, dtype=torch.long)
    lab[0, 3, 1:8] = 3
    w = boundary_weights(lab, 4.0)
    assert bool((w[0, 3, 1:8] == 5.0).all()) and bool((w[0, 2:5, 0:9] == 5.0).all())
    assert bool((w[0, :2] == 1.0).all()) and bool((w[0, 5:] == 1.0).all())


def test_pixel_weighted_cross_entropy_by_hand():
    logits = torch.tensor([[[[0.0, 1.0, 2.0]], [[0.0, 0.0, 0.0]]]])  # (1, 2, 1, 3)
    label = torch.tensor([[[0, 1, IGNORE]]])
    pw = torch.tensor([[[3.0, 1.0, 100.0]]])
    nll = torch.tensor([torch.log(torch.tensor(2.0)), torch.log1p(torch.exp(torch.tensor(1.0)))])
    want = float((3 * nll[0] + 1 * nll[1]) / 4)
    assert float(cross_entropy(logits, label, pixel_weight=pw)) == pytest.approx(want, rel=1e-6)
    cw = torch.tensor([1.0, 2.0])
    want_cw = float((3 * nll[0] + 2 * nll[1]) / 5)
    assert float(cross_entropy(logits, label, cw, pixel_weight=pw)) == pytest.approx(want_cw, rel=1e-6)


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 1000))
def test_uniform_pixel_weight_is_the_plain_loss(seed):
    g = torch.Generator().manual_seed(seed)
    x, y = torch.randn(2, 4, 5, 6, generator=g), torch.randint(0, 4, (2, 5, 6), generator=g)
    y[1, 2, 3] = IGNORE
    w = torch.rand(4, generator=g) + 0.5
    ones = torch.full(y.shape, 2.5)
    for gamma in (0.0, 2.0):
        assert float(cross_entropy(x, y, w, gamma=gamma, pixel_weight=ones)) == pytest.approx(
            float(cross_entropy(x, y, w, gamma=gamma)), rel=1e-5)
    # a constant label map has no boundary: the weights are all 1
    assert torch.equal(boundary_weights(torch.full((1, 5, 6), int(y[0, 0, 0])), 3.0), torch.ones(1, 5, 6))


@torch.no_grad()
def test_seg_step_channels_last_and_boundary():
    from cadalign.models.resunet import ResUNet, ResUNetConfig
    from cadalign.train.seg import seg_step

    torch.manual_seed(0)
    model = ResUNet(3, ResUNetConfig(base_channels=4, depth=3)).eval()
    batch = {"image": torch.rand(2, 3, 16, 24), "label": torch.randint(0, 3, (2, 16, 24))}
    plain, _ = seg_step(None, 0.5)(model, batch)
    cl_model = ResUNet(3, ResUNetConfig(base_channels=4, depth=3)).eval()
    cl_model.load_state_dict(model.state_dict())
    cl_model = cl_model.to(memory_format=torch.channels_last)
    cl, _ = seg_step(None, 0.5, channels_last=True)(cl_model, batch)
    assert float(cl) == pytest.approx(float(plain), rel=1e-5)  # same maths in another memory layout
    bnd, m = seg_step(None, 0.0, boundary=(2.0, 1))(model, batch)
    ce_bnd = cross_entropy(model(batch["image"]), batch["label"],
                           pixel_weight=boundary_weights(batch["label"], 2.0))
    assert float(bnd) == pytest.approx(float(ce_bnd), rel=1e-6) and m["ce"] == pytest.approx(float(bnd), rel=1e-6)


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000), st.integers(0, 100_000))
def test_augment_step_inverts_the_loop_seed(seed, step):
    from cadalign.train.loop import augment_seed
    from cadalign.train.seg import augment_step

    assert augment_step(torch.Generator().manual_seed(augment_seed(seed, step, 0)), seed) == step


def test_full_frame_phase_takes_whole_frames_at_the_end():
    from cadalign.train.loop import LoopConfig, augment_seed
    from cadalign.train.seg import SegTrainConfig, _patches

    cfg = SegTrainConfig(patch=(8, 12), full_frame_fraction=0.25, full_frame_batch=2,
                         loop=LoopConfig(steps=8, batch_size=3, seed=3))
    batch = {"image": torch.rand(3, 3, 20, 30), "label": torch.randint(0, 4, (3, 20, 30)),
             "im_id": torch.tensor([4, 5, 6])}
    shapes = []
    for step in range(8):
        out = _patches(batch, torch.Generator().manual_seed(augment_seed(3, step, 0)), cfg, None)
        shapes.append(tuple(out["label"].shape))
    assert shapes == [(3, 8, 12)] * 6 + [(2, 20, 30)] * 2  # round(0.25 * 8) = 2 final steps
    assert torch.equal(out["image"], batch["image"][:2]) and out["im_id"].tolist() == [4, 5]
    none = SegTrainConfig(patch=None, loop=LoopConfig(steps=8, batch_size=3, seed=3))
    assert _patches(batch, torch.Generator().manual_seed(augment_seed(3, 0, 0)), none, None) is batch


def test_tiny_seg_run_with_boundary_and_full_frame_phase(tiny_dense, tmp_path):
    import json

    from cadalign.models.resunet import ResUNetConfig
    from cadalign.train.augment import AugmentConfig
    from cadalign.train.loop import LoopConfig
    from cadalign.train.seg import SegTrainConfig, train_seg

    cfg = SegTrainConfig(model=ResUNetConfig(base_channels=4, depth=3), scale=0.5, patch=(24, 32),
                         augment=AugmentConfig(enabled=False), boundary_boost=2.0, full_frame_fraction=0.5,
                         loop=LoopConfig(steps=6, batch_size=2, lr=1e-2, checkpoint_every=3, log_every=1, warmup=0.0))
    res = train_seg(cfg, tiny_dense, tmp_path / "seg", val_split=None)
    rows = json.loads((tmp_path / "seg" / "metrics.json").read_text())["rows"]
    assert res.steps_done == 6 and len(rows) == 6 and all(math.isfinite(r["loss"]) for r in rows)
    rec = json.loads((tmp_path / "seg" / "train_config.json").read_text())
    assert rec["config"]["full_frame_fraction"] == 0.5 and rec["config"]["channels_last"] is True

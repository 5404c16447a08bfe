"""Zoom-in windows (targets stay aligned, nearest-neighbour labels, depth / z) and the lamp hotspot."""

from __future__ import annotations

import json

import pytest
import torch

from cadalign.train.augment import AugmentConfig, augment_dense, lamp_hotspot, random_patches, zoom_windows


def _coded(h: int = 40, w: int = 60, b: int = 4) -> dict:
    """A batch whose image, label and depth all encode the pixel position (label in 4x5 blocks)."""
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    label = ((yy // 4) * 7 + xx // 5) % 250
    image = torch.stack([label / 250.0, yy / h, xx / w]).float()[None].repeat(b, 1, 1, 1)
    depth = (yy * w + xx).float()[None, None].repeat(b, 1, 1, 1) + 1
    return {"image": image, "label": label[None].repeat(b, 1, 1), "depth": depth, "valid": depth > 0,
            "im_id": torch.arange(b)}


def test_zoom_by_two_repeats_each_source_pixel_and_scales_depth():
    batch = _coded(b=1)
    # window of 8x10 source pixels starting at (6, 12): centre (10, 17), zoom 2 -> 16x20 output
    out = zoom_windows(batch, [(10.0, 17.0)], [2.0], (16, 20))
    want = batch["label"][0, 6:14, 12:22].repeat_interleave(2, 0).repeat_interleave(2, 1)
    assert out["label"].dtype == batch["label"].dtype and torch.equal(out["label"][0], want)
    want_d = batch["depth"][0, 0, 6:14, 12:22].repeat_interleave(2, 0).repeat_interleave(2, 1) / 2
    assert torch.allclose(out["depth"][0, 0], want_d)
    assert out["valid"].dtype == torch.bool and bool(out["valid"].all())
    # the image is sampled at the same points (bilinear): its x coordinate channel is the source x of each pixel
    x_src = (torch.arange(20) + 0.5) / 2 + 12 - 0.5  # output pixel centre -> source pixel index (continuous)
    assert torch.allclose(out["image"][0, 2, 8] * 60, x_src, atol=1e-4)


def test_zoom_window_is_clamped_inside_the_frame():
    batch = _coded(b=1)
    out = zoom_windows(batch, [(0.0, 0.0)], [2.0], (16, 20))  # a corner centre: the window starts at (0, 0)
    assert torch.equal(out["label"][0, ::2, ::2], batch["label"][0, :8, :10])


def test_random_zoomed_patches_keep_labels_aligned_and_focus():
    batch = _coded()
    batch["label"][:, 37, 55] = 251  # one rare pixel in a corner (kept by the nearest-neighbour resampling)
    g = torch.Generator().manual_seed(0)
    out = random_patches(batch, g, (16, 20), focus_prob=1.0, focus_weights=[0.0] * 251 + [1.0], zoom_prob=1.0,
                         zoom_max=3.0)
    assert out["image"].shape == (4, 3, 16, 20) and out["label"].shape == (4, 16, 20)
    assert bool((out["label"] == 251).flatten(1).any(1).all())  # the zoomed window still holds the focus pixel
    lab = out["label"].float()
    # where a pixel's 7x7 neighbourhood (one source pixel either side at zoom <= 3) has one label, the bilinear
    # image equals the label code exactly (the window's 3-pixel rim is left out: its outer neighbours are unseen)
    nb = lab[:, None].unfold(2, 7, 1).unfold(3, 7, 1).flatten(-2)[:, 0]
    inner = lab[:, 3:-3, 3:-3]
    flat = (nb == inner[..., None]).all(-1) & (inner < 250)
    assert flat.sum() > 50
    assert torch.allclose(out["image"][:, 0, 3:-3, 3:-3][flat] * 250, inner[flat], atol=1e-3)
    # some windows really were magnified: a source 4x5 block spans more than 4 rows there
    assert int((out["label"][:, :, 10] == out["label"][:, :1, 10]).sum(1).max()) > 4


def test_zoom_off_keeps_the_old_windows_and_random_stream():
    batch = _coded()
    a = random_patches(batch, torch.Generator().manual_seed(4), (16, 20), 0.5)
    b = random_patches(batch, torch.Generator().manual_seed(4), (16, 20), 0.5, zoom_prob=0.0, zoom_max=3.0)
    assert all(torch.equal(a[k], b[k]) for k in ("image", "label", "depth"))
    full = random_patches(batch, torch.Generator().manual_seed(4), (40, 60), 0.5, zoom_prob=1.0, zoom_max=2.0)
    assert full["image"].shape == (4, 3, 40, 60) and not torch.equal(full["label"], batch["label"])


def test_lamp_hotspot_centres_on_the_weighted_class():
    image = torch.full((3, 3, 30, 40), 0.2)
    label = torch.zeros(3, 30, 40, dtype=torch.long)
    label[:, 5:, :] = 1
    label[:, 22, 31] = 3
    cfg = AugmentConfig(lamp_prob=1.0, lamp_gain=2.0, lamp_sigma=(0.1, 0.2))
    out = lamp_hotspot(image, torch.Generator().manual_seed(0), cfg, label, [0.0, 0.0, 0.0, 1.0])
    gain = out / image
    assert float(gain.min()) >= 1.0 - 1e-6 and float(gain.max()) <= 3.0 + 1e-5
    peak = gain.amax(1).flatten(1).argmax(1)  # brightest pixel of each sample: the class-3 pixel
    assert peak.tolist() == [22 * 40 + 31] * 3
    off = lamp_hotspot(image, torch.Generator().manual_seed(0), AugmentConfig(lamp_prob=0.0), label, [0, 0, 0, 1])
    assert torch.equal(off, image)
    # no weighted class present: a uniform centre, still a valid image
    free = lamp_hotspot(torch.rand(2, 3, 8, 9), torch.Generator().manual_seed(1), cfg, label[:2, :8, :9], [0, 0, 1, 0])
    assert float(free.min()) >= 0 and float(free.max()) <= 1


def test_augment_with_lamp_off_is_unchanged():
    batch = _coded()
    a = augment_dense(batch, torch.Generator().manual_seed(2), AugmentConfig())
    b = augment_dense(batch, torch.Generator().manual_seed(2), AugmentConfig(lamp_gain=3.0), [0, 1, 1, 1])
    assert torch.equal(a["image"], b["image"]) and torch.equal(a["label"], b["label"])
    c = augment_dense(batch, torch.Generator().manual_seed(2), AugmentConfig(lamp_prob=1.0), [0, 1, 1, 1])
    assert torch.equal(a["label"], c["label"]) and not torch.equal(a["image"], c["image"])


def test_tiny_seg_run_with_zoom_and_lamp(tiny_dense, tmp_path):
    from cadalign.models.resunet import ResUNetConfig
    from cadalign.train.loop import LoopConfig
    from cadalign.train.seg import SegTrainConfig, lamp_weights, train_seg

    assert lamp_weights([0.5, 0.1, 0.2], 3) == [0.0, 0.1, 0.2] and lamp_weights(None, 3) == [0.0, 1.0, 1.0]
    cfg = SegTrainConfig(model=ResUNetConfig(base_channels=4, depth=3), scale=0.5, patch=(24, 32), zoom_prob=1.0,
                         zoom_max=2.5, augment=AugmentConfig(lamp_prob=1.0),
                         loop=LoopConfig(steps=3, batch_size=2, lr=1e-2, checkpoint_every=3, log_every=1))
    res = train_seg(cfg, tiny_dense, tmp_path / "seg", val_split=None)
    assert res.steps_done == 3
    rec = json.loads((tmp_path / "seg" / "train_config.json").read_text())
    assert rec["config"]["zoom_prob"] == 1.0 and rec["config"]["augment"]["lamp_prob"] == 1.0


@pytest.mark.parametrize("bad", [{"zoom_max": 0.5}, {"zoom_prob": 1.5}])
def test_zoom_fields_are_bounded(bad):
    from cadalign.config import from_dict
    from cadalign.errors import ConfigError
    from cadalign.train.seg import SegTrainConfig

    with pytest.raises(ConfigError):
        from_dict(SegTrainConfig, bad, source="test")

"""Seg and depth trainers on a tiny simulated scene: loss decreases, identity checks, inference helpers."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from cadalign.config import from_dict
from cadalign.errors import ConfigError, InputError, TrainingError
from cadalign.infer.dense import load_dense_model, metric_depth, seg_probabilities
from cadalign.io import read_json
from cadalign.models.dispnet import DispNetConfig
from cadalign.models.resunet import ResUNetConfig
from cadalign.train.augment import AugmentConfig
from cadalign.train.data import select
from cadalign.train.depth import DepthTrainConfig, train_depth
from cadalign.train.loop import LoopConfig
from cadalign.train.seg import SegTrainConfig, train_seg

LOOP = LoopConfig(steps=14, batch_size=2, lr=1e-2, checkpoint_every=7, log_every=1, warmup=0.0)
NO_AUG = AugmentConfig(enabled=False)


def _losses(run: Path) -> list[float]:
    return [r["loss"] for r in read_json(run / "metrics.json")["rows"]]


def test_derived_split_of_a_bare_scene(tiny_dense):
    parts = {s: select(tiny_dense, s).ids for s in ("train", "val", "test")}
    assert sorted(sum(map(list, parts.values()), [])) == list(range(6))
    assert len(parts["train"]) == 4 and len(parts["val"]) == 1 and len(parts["test"]) == 1
    with pytest.raises(InputError, match="unknown split"):
        select(tiny_dense, "holdout")
    with pytest.raises(InputError, match="neither a dataset root"):
        select(tiny_dense / "rgb", "train")


def test_seg_trains_and_predicts(tiny_dense, tmp_path):
    cfg = SegTrainConfig(model=ResUNetConfig(base_channels=4, depth=3), loop=LOOP, augment=NO_AUG, scale=0.5,
                         patch=(48, 64))
    res = train_seg(cfg, tiny_dense, tmp_path / "seg")
    losses = _losses(tmp_path / "seg")
    assert res.steps_done == 14 and np.mean(losses[-3:]) < 0.7 * np.mean(losses[:3])
    rec = read_json(tmp_path / "seg" / "train_config.json")
    assert rec["classes"] == ["background", "structure", "valve", "hot_stab"] and rec["model"]["base_channels"] == 4
    assert rec["images"] == {"enhance": "none"}  # a simulator's frames are raw
    assert "val_miou" in read_json(tmp_path / "seg" / "metrics.json")["rows"][-1]
    dm = load_dense_model(tmp_path / "seg", task="seg")
    probs = seg_probabilities(dm, np.zeros((120, 160, 3), np.uint8))
    assert probs.shape == (1, 4, 120, 160) and torch.allclose(probs.sum(1), torch.ones(1, 120, 160), atol=1e-5)
    with pytest.raises(InputError, match="depth model"):
        metric_depth(dm, np.zeros((120, 160, 3), np.uint8))


def test_depth_trains_with_mask_input(tiny_dense, tmp_path):
    cfg = DepthTrainConfig(model=DispNetConfig(base_channels=4, levels=3), loop=replace(LOOP, lr=5e-3),
                           augment=NO_AUG, scale=0.5, mask_input=True, grad_weight=0.2)
    res = train_depth(cfg, tiny_dense, tmp_path / "depth")
    losses = _losses(tmp_path / "depth")
    assert res.steps_done == 14 and np.mean(losses[-3:]) < 0.7 * np.mean(losses[:3])
    rec = read_json(tmp_path / "depth" / "train_config.json")
    lo, hi = rec["depth_range_m"]
    assert 0 < lo < hi and rec["model"]["in_channels"] == 4
    dm = load_dense_model(tmp_path / "depth")
    with pytest.raises(InputError, match="fg_mask"):
        metric_depth(dm, torch.rand(3, 120, 160))
    d = metric_depth(dm, torch.rand(3, 120, 160), fg_mask=np.ones((120, 160), bool))
    assert d.shape == (1, 120, 160) and float(d.min()) >= lo - 1e-4 and float(d.max()) <= hi + 1e-3


def test_resume_refuses_other_classes_and_other_config(tiny_dense, tmp_path):
    cfg = SegTrainConfig(model=ResUNetConfig(base_channels=4, depth=3), loop=replace(LOOP, steps=2), augment=NO_AUG)
    train_seg(cfg, tiny_dense, tmp_path / "run", val_split=None)
    other = tmp_path / "other_scene"
    shutil.copytree(tiny_dense, other)
    objects = json.loads((other / "objects.json").read_text())
    objects["classes"] = ["background", "structure", "pipe", "hot_stab"]
    (other / "objects.json").write_text(json.dumps(objects))
    with pytest.raises(TrainingError, match=r"different classes.*'valve'.*'pipe'"):
        train_seg(replace(cfg, loop=replace(cfg.loop, steps=4)), other, tmp_path / "run", resume=True, val_split=None)
    with pytest.raises(TrainingError, match="trained on classes"):
        load_dense_model(tmp_path / "run", classes=objects["classes"])
    with pytest.raises(TrainingError, match="'seg' model, not 'depth'"):
        load_dense_model(tmp_path / "run", task="depth")
    with pytest.raises(ConfigError, match="dice_weight"):
        train_seg(replace(cfg, dice_weight=0.0), tiny_dense, tmp_path / "run", resume=True, val_split=None)
    with pytest.raises(ConfigError, match="--resume"):
        train_seg(cfg, tiny_dense, tmp_path / "run", val_split=None)
    longer = train_seg(replace(cfg, loop=replace(cfg.loop, steps=3)), tiny_dense, tmp_path / "run", resume=True,
                       val_split=None)
    assert longer.steps_done == 3
    # --overwrite starts the run again with the other config (and other classes)
    again = train_seg(replace(cfg, dice_weight=0.0), other, tmp_path / "run", overwrite=True, val_split=None)
    assert again.steps_done == 2
    record = read_json(tmp_path / "run" / "train_config.json")
    assert record["config"]["dice_weight"] == 0.0 and record["classes"] == objects["classes"]
    assert max(r["step"] for r in read_json(tmp_path / "run" / "metrics.json")["rows"]) == 2


def test_preset_config_file_is_strict(tmp_path):
    with pytest.raises(ConfigError, match="did you mean 'model.base_channels'"):
        from_dict(SegTrainConfig, {"model": {"base_channel": 4}}, source="x.toml")
    with pytest.raises(ConfigError, match="loss"):
        from_dict(DepthTrainConfig, {"loss": "huber"}, source="x.toml")


@pytest.mark.parametrize("name", ["seg_tiny", "seg_small_classes", "seg_thesis_weights", "seg_fast_240x320",
                                  "seg_zoom_lamp", "seg_fast_fp32", "seg_fast_s10", "depth_tiny", "depth_thesis",
                                  "depth_silog_mask"])
def test_training_configs_load(repo_root, name):
    from cadalign.config import resolve
    from cadalign.train import depth, seg

    mod, cls = (seg, SegTrainConfig) if name.startswith("seg") else (depth, DepthTrainConfig)
    for preset in mod.PRESETS:
        cfg = resolve(cls, mod.PRESETS, preset, repo_root / "training" / f"{name}.toml")
        assert isinstance(cfg, cls)


def test_the_fast_seg_preset_autocasts_and_its_fp32_config_does_not(repo_root):
    from cadalign.config import resolve
    from cadalign.train import seg

    assert seg.PRESETS["fast"].loop.amp
    for name in ("seg_fast_fp32", "seg_fast_240x320"):
        assert not resolve(SegTrainConfig, seg.PRESETS, "fast", repo_root / "training" / f"{name}.toml").loop.amp

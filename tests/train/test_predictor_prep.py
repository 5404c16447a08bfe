"""Fusion's network predictors prepare raw frames as the network's training images were (``image_prep``)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from cadalign.fuse.predictors import depth_predictor, seg_predictor
from cadalign.infer.dense import load_dense_model, metric_depth, seg_probabilities
from cadalign.io import read_json, write_json
from cadalign.models.dispnet import DispNetConfig
from cadalign.models.resunet import ResUNetConfig
from cadalign.sfm.config import FrameConfig
from cadalign.sfm.frames import enhance
from cadalign.sfm.image_prep import RAW, prep_named, to_feed
from cadalign.train.augment import AugmentConfig
from cadalign.train.depth import DepthTrainConfig, train_depth
from cadalign.train.loop import LoopConfig
from cadalign.train.seg import SegTrainConfig, train_seg
from cadalign.types import Camera

LOOP = LoopConfig(steps=4, batch_size=2, lr=1e-2, checkpoint_every=4, log_every=1, warmup=0.0)
CLAHE = prep_named("clahe")


def _as_trained_on(run: Path, prep: dict) -> Path:
    """Say in the run's record that its training images were prepared as ``prep``."""
    rec = read_json(run / "train_config.json")
    write_json(run / "train_config.json", {**rec, "images": prep})
    return run


@pytest.fixture(scope="module")
def runs(tiny_dense: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("prep_runs")
    aug = AugmentConfig(enabled=False)
    train_seg(SegTrainConfig(model=ResUNetConfig(base_channels=4, depth=3), loop=LOOP, augment=aug, scale=0.5,
                             patch=(48, 64)), tiny_dense, root / "seg", val_split=None)
    train_depth(DepthTrainConfig(model=DispNetConfig(base_channels=4, levels=3), loop=LOOP, augment=aug, scale=0.5),
                tiny_dense, root / "depth")
    return _as_trained_on(root / "seg", CLAHE), _as_trained_on(root / "depth", CLAHE)


def _frame(tiny_dense: Path) -> np.ndarray:
    """The scene's first frame, read as fusion reads it."""
    from cadalign.formats.bop import BopScene

    scene = BopScene(tiny_dense)
    return scene.rgb(scene.ids[0])


def test_raw_frames_are_enhanced_as_the_training_images_were(runs, tiny_dense: Path) -> None:
    seg_run, depth_run = runs
    rgb = _frame(tiny_dense)
    clahe = enhance(rgb, FrameConfig(enhance="clahe"))
    assert not np.array_equal(rgb, clahe)
    dm = load_dense_model(seg_run, task="seg")
    seg_raw = seg_predictor(seg_run, dm.classes, source_prep=dict(RAW))
    np.testing.assert_array_equal(seg_raw(rgb), seg_probabilities(dm, clahe)[0].numpy())
    seg_same = seg_predictor(seg_run / "checkpoints" / "last.pt", dm.classes, source_prep=CLAHE)  # already alike
    np.testing.assert_array_equal(seg_same(clahe), seg_probabilities(dm, clahe)[0].numpy())
    cam = Camera(np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]]), rgb.shape[1], rgb.shape[0])
    ddm = load_dense_model(depth_run, task="depth")
    got = depth_predictor(depth_run, source_prep=dict(RAW))(rgb, cam)
    np.testing.assert_array_equal(got, metric_depth(ddm, clahe)[0].numpy())
    assert not np.array_equal(got, metric_depth(ddm, rgb)[0].numpy())


def test_an_enhancement_the_network_never_saw_is_not_undone_but_said(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING):
        assert to_feed(CLAHE, dict(RAW), "RUN") == RAW
    assert "RUN" in caplog.text and "fed as they are" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert to_feed(None, CLAHE, "RUN") == RAW and to_feed(CLAHE, None, "RUN") == RAW  # unknown: nothing done
    assert caplog.text == ""  # an enhanced source for a silent run: nothing to say
    with caplog.at_level(logging.WARNING):
        assert to_feed(dict(RAW), None, "OLDRUN") == RAW  # raw frames, a run that does not say: fed raw, said
    assert "OLDRUN does not record" in caplog.text
    wb = prep_named("clahe_wb")
    assert to_feed(dict(RAW), wb, "RUN") == wb and to_feed(CLAHE, CLAHE, "RUN") == RAW


def test_emulate_prepares_an_image_source_as_the_networks_training_images(runs, tiny_dense: Path) -> None:
    """``cadalign emulate ... --model-seg/--model-depth``: a simulator's raw frame gets the CLAHE the networks
    were trained with (the source's preparation is read from its scene), like fusion's predictors."""
    from cadalign.cli.emulate import _predictors
    from cadalign.formats.bop import BopScene

    seg_run, depth_run = runs
    scene = BopScene(tiny_dense)
    im = scene.ids[0]
    kw = _predictors(depth_run, seg_run, "cpu", tiny_dense / "rgb" / f"{im:06d}.png")
    rgb = scene.rgb(im)
    clahe = enhance(rgb, FrameConfig(enhance="clahe"))
    dm = load_dense_model(seg_run, task="seg")
    np.testing.assert_array_equal(kw["seg_fn"](rgb), seg_probabilities(dm, clahe)[0].numpy())
    assert not np.array_equal(kw["seg_fn"](rgb.copy()), seg_probabilities(dm, rgb)[0].numpy())
    cam = Camera(np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]]), rgb.shape[1], rgb.shape[0])
    np.testing.assert_array_equal(kw["depth_fn"](rgb, cam),
                                  metric_depth(load_dense_model(depth_run, task="depth"), clahe)[0].numpy())
    assert kw["models"] == {"depth": str(depth_run), "seg": str(seg_run)}


def test_emulate_networks_given_with_a_scene_or_mesh_source_are_refused(runs, tmp_path: Path) -> None:
    """The networks serve image sources; a scene or mesh source has exact depth and classes, so a network given
    with one would be built and never asked: that is an error naming the option, not silence."""
    from cadalign.cli.emulate import _predictors
    from cadalign.errors import InputError

    seg_run, depth_run = runs
    with pytest.raises(InputError, match=r"scene\.toml: --model-seg replace.*Drop the option"):
        _predictors(None, seg_run, "cpu", tmp_path / "scene.toml")
    with pytest.raises(InputError, match=r"map\.ply: --model-depth and --model-seg replace"):
        _predictors(depth_run, seg_run, "cpu", tmp_path / "map.ply")
    assert _predictors(None, None, "cpu", tmp_path / "scene.toml") == {}

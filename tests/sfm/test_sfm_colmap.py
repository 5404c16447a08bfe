"""pycolmap steps: masks reach the extractor, pose-guided loop pairs, reasons for unregistered frames."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pycolmap

from cadalign.io import write_image
from cadalign.sfm import PRESETS
from cadalign.sfm.colmap import classify_unregistered, extract_features
from cadalign.sfm.config import MatchConfig, SfMConfig
from cadalign.sfm.refine import loop_pairs

# the doubled first octave: 'fast' starts SIFT at the image's own size, which on these 160x120 textures finds
# 44-56 features (under features.min_features), not enough to test the masks with
CFG = dataclasses.replace(PRESETS["fast"], num_threads=1,
                          features=dataclasses.replace(PRESETS["fast"].features, first_octave=-1))


def _texture(seed: int, h: int = 120, w: int = 160) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 255, (h // 4, w // 4, 3), dtype=np.uint8)
    return cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)


def test_masks_remove_features(tmp_path):
    images, masks = tmp_path / "images", tmp_path / "masks"
    names = [f"{k:06d}.png" for k in range(3)]
    for k, name in enumerate(names):
        write_image(images / name, _texture(k))
        mask = np.full((120, 160), 255, np.uint8)
        mask[:, :80] = 0  # left half is ROV hardware
        write_image(masks / f"{name}.png", mask)
    extract_features(CFG, tmp_path / "db.db", images, names, masks)
    with pycolmap.Database.open(tmp_path / "db.db") as db:
        for im in db.read_all_images():
            kp = db.read_keypoints(im.image_id)
            assert len(kp) > 20 and kp[:, 0].min() >= 78  # none in the masked half (SIFT sub-pixel slack)
        assert db.num_cameras() == 1  # one shared camera


def _orbit(n: int) -> tuple[list[str], np.ndarray, np.ndarray]:
    a = 2 * np.pi * np.arange(n) / n
    C = np.stack([10 * np.cos(a), 10 * np.sin(a), np.zeros(n)], 1)
    V = -C / 10.0
    return [f"{k:06d}.png" for k in range(n)], C, V


def test_loop_pairs_close_the_orbit_but_skip_symmetric_views():
    names, C, V = _orbit(64)
    cfg = dataclasses.replace(SfMConfig(), matching=MatchConfig(overlap=10))
    pairs = loop_pairs(names, C, V, {n: k for k, n in enumerate(names)}, cfg)
    assert pairs and ("000000.png", "000063.png") in pairs
    for a, b in pairs:  # only the wrap-around: frames 90 deg (16 frames) apart look alike but are far
        gap = abs(int(a[:6]) - int(b[:6]))
        assert min(gap, 64 - gap) <= 13
    # an open path (no return) has no loop pairs
    assert loop_pairs(names[:30], C[:30], V[:30], {n: k for k, n in enumerate(names)}, cfg) == []


def test_unregistered_reasons_name_the_cause():
    cfg = SfMConfig()
    names = ["a.png", "b.png", "c.png", "d.png", "e.png", "f.png"]
    registered = [{"a.png", "b.png"}, {"e.png", "f.png", "x.png"}]
    n_features = {"a.png": 900, "b.png": 900, "c.png": 3, "d.png": 800, "e.png": 700, "f.png": 700}
    best = {"a.png": 300, "b.png": 300, "d.png": 4, "e.png": 80, "f.png": 80}
    reasons = classify_unregistered(names, registered, n_features, best, cfg)
    assert reasons == {
        "c.png": f"too few features (3 < {cfg.features.min_features})",
        "d.png": "no matches (best pair has 4 verified matches)",
        "e.png": "in disconnected model 1 (3 frames)",
        "f.png": "in disconnected model 1 (3 frames)",
    }
    reasons = classify_unregistered(["g.png"], [set()], {"g.png": 500}, {"g.png": 100}, cfg)
    assert reasons == {"g.png": "not registered (the mapper could not localise it)"}

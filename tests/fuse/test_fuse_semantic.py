"""Log-domain Bayes update: exact values, extremes, and stability over thousands of conflicting frames."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.errors import InputError
from cadalign.fuse.base import FuseFrame, probs_from_stored
from cadalign.fuse.config import FuseConfig
from cadalign.fuse.semantic import bayes_update, clamped_log_probs, probs_from_labels
from cadalign.fuse.surfel import SurfelMap
from cadalign.fuse.tsdf import SemanticTSDF
from cadalign.types import Camera, Rigid3


def test_bayes_update_exact_hand_case() -> None:
    # uniform prior x (0.7, 0.2, 0.1) -> the observation itself; stored relative to the mode
    obs = np.log(np.array([[0.7, 0.2, 0.1]], np.float32))
    out = bayes_update(np.zeros((1, 3), np.float32), obs, log_floor=-20.0)
    np.testing.assert_allclose(out, [[0.0, math.log(2 / 7), math.log(1 / 7)]], atol=1e-6)
    # a second identical observation squares the likelihood: p ∝ (0.49, 0.04, 0.01)
    out2 = bayes_update(out, obs, log_floor=-20.0)
    p = probs_from_stored(out2)[0]
    np.testing.assert_allclose(p, np.array([0.49, 0.04, 0.01]) / 0.54, rtol=1e-5)


def test_floor_and_clamp() -> None:
    obs = clamped_log_probs(np.array([[1.0, 0.0, np.nan, np.inf]]), min_prob=1e-3)
    np.testing.assert_allclose(obs, np.log([[1.0, 1e-3, 1e-3, 1.0]]), rtol=1e-6)
    s = np.zeros((1, 4), np.float32)
    for _ in range(100):
        s = bayes_update(s, obs, log_floor=-5.0)
    assert s.max() == 0 and s.min() >= -5.0


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=3, max_size=3),
       st.floats(-50, -0.5))
def test_update_is_finite_for_any_input(raw: list[float], floor: float) -> None:
    stored = np.array([[0.0, floor, floor / 2]], np.float32)
    out = bayes_update(stored, clamped_log_probs(np.array([raw]), 1e-4), floor)
    assert np.isfinite(out).all() and out.max() == 0 and out.min() >= np.float32(floor)
    p = probs_from_stored(out)
    assert np.isfinite(p).all() and abs(p.sum() - 1) < 1e-6


def test_probs_from_labels_exact_and_errors() -> None:
    p = probs_from_labels(np.array([[0, 2]]), 3, confidence=0.9)
    np.testing.assert_allclose(p[:, 0, 0], [0.9, 0.05, 0.05])
    np.testing.assert_allclose(p[:, 0, 1], [0.05, 0.05, 0.9])
    with pytest.raises(InputError, match=r"label values must lie in \[0, 2\]"):
        probs_from_labels(np.array([[3]]), 3, 0.9)


def _plane_frame(cls: int, n_classes: int = 3, size: int = 16) -> FuseFrame:
    """A frontal plane 1.013 m away (not on a voxel layer) seen by a tiny camera, all pixels labelled ``cls``."""
    cam = Camera(np.array([[size, 0, size / 2], [0, size, size / 2], [0, 0, 1]]), size, size)
    probs = np.full((n_classes, size, size), 0.0005, np.float32)
    probs[cls] = 0.999
    return FuseFrame(np.full((size, size), 1.013, np.float32), probs, cam, Rigid3(), None)


@pytest.mark.parametrize("cls_map, frames", [(SemanticTSDF, 5000), (SurfelMap, 5000)])
def test_thousands_of_conflicting_frames_stay_finite_and_normalised(cls_map: type, frames: int) -> None:
    cfg = FuseConfig(voxel_m=0.05, block_resolution=4, block_count=64, method="tsdf" if cls_map is SemanticTSDF
                     else "surfel", surfel_min_confidence=0.1)
    m = cls_map(cfg, 3)
    # confident and conflicting: every frame is 99.9% sure, two in three say class 0, one says class 1
    conflicting = [_plane_frame(0), _plane_frame(0), _plane_frame(1)]
    for k in range(frames):
        m.integrate(conflicting[k % 3])
    assert m.frames_integrated == frames
    stored = m.state()["label"].reshape(-1, 3)
    assert np.isfinite(stored).all() and stored.max() <= 0 and stored.min() >= cfg.label_log_floor - 1e-4
    pts = m.extract_points()
    assert len(pts) > 0 and np.isfinite(pts.probs).all()
    np.testing.assert_allclose(pts.probs.sum(axis=1), 1.0, atol=1e-5)
    # the majority wins, although the last frame said class 1; the floor keeps every class possible
    assert np.mean(pts.labels == 0) > 0.9
    assert pts.probs.min() > 0
    observed = stored[np.any(stored != 0, axis=1)]
    assert len(observed) > 0 and np.all(observed[:, 0] == 0) and np.all(observed[:, 1:] < -5)

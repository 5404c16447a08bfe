"""The ground-truth-free hinge/fold check of an SfM model (consecutive-frame epipolar consistency)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from sfm_synthetic import synthetic_model

from cadalign.sfm.consistency import Break, Consistency, keep_largest_piece, pieces, sampson_px, sequence_consistency


def _two_views(rng: np.random.Generator, n: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    X = rng.uniform([-2, -2, 6], [2, 2, 10], size=(n, 3))
    R = Rotation.from_euler("y", 8, degrees=True).as_matrix()
    t = np.array([-0.9, 0.05, 0.1])
    Xb = X @ R.T + t
    return X[:, :2] / X[:, 2:], Xb[:, :2] / Xb[:, 2:], R, t


def test_sampson_is_zero_for_the_true_pose_and_grows_with_a_wrong_rotation():
    xa, xb, R, t = _two_views(np.random.default_rng(0))
    assert sampson_px(xa, xb, R, t, 500.0).max() < 1e-9
    assert sampson_px(xa, xb, R, 3.0 * t, 500.0).max() < 1e-9  # translation scale is irrelevant
    wrong = Rotation.from_euler("x", 1.0, degrees=True).as_matrix() @ R
    assert np.median(sampson_px(xa, xb, wrong, t, 500.0)) > 2.0  # 1 deg at f = 500 px is ~8.7 px of motion


def test_sampson_without_baseline_says_nothing():
    xa, xb, R, _ = _two_views(np.random.default_rng(1), 5)
    assert np.isinf(sampson_px(xa, xb, R, np.zeros(3), 500.0)).all()
    assert np.isinf(sampson_px(xa, xb, R, np.array([np.nan, 0, 0]), 500.0)).all()


@settings(max_examples=30, deadline=None)
@given(st.lists(st.integers(0, 11), max_size=5, unique=True), st.lists(st.integers(0, 11), max_size=4, unique=True))
def test_pieces_partition_the_registered_frames(cut_at: list[int], unregistered: list[int]):
    names = [f"{k:06d}" for k in range(12)]
    reg = {n for k, n in enumerate(names) if k not in unregistered}
    seq = [n for n in names if n in reg]
    breaks = [Break(seq[i - 1], seq[i], 100, 9.0) for i in cut_at if 0 < i < len(seq)]
    parts = pieces(names, reg, breaks)
    assert [n for p in parts for n in p] == seq  # every registered frame once, in order
    assert len(parts) == (1 if seq else 0) + len(breaks)


@pytest.fixture()
def synthetic(tmp_path: Path) -> tuple[pycolmap.Reconstruction, Path, list[str]]:
    """A pycolmap synthetic model (8 frames) and its database of exact verified matches."""
    db_path = tmp_path / "database.db"
    rec = synthetic_model(db_path, frames=8, points=400, seed=3)
    names = sorted(im.name for im in rec.images.values())
    return rec, db_path, names


def test_a_sound_model_has_no_breaks(synthetic):
    rec, db, names = synthetic
    cons = sequence_consistency(rec, db, names, min_matches=20)
    assert cons.pairs_checked >= 5 and cons.ok and cons.max_px < 1e-3


def test_a_hinge_is_found_where_it_is_and_the_largest_piece_is_kept(synthetic):
    rec, db, names = synthetic
    by_name = {im.name: im for im in rec.images.values()}
    turn = pycolmap.Rotation3d(Rotation.from_euler("z", 5, degrees=True).as_quat())
    hinge = pycolmap.Rigid3d(turn, np.zeros(3))  # turn frames 5.. about the world origin: a hinge at 4/5
    for n in names[5:]:
        im = by_name[n]
        rec.frames[im.frame_id].rig_from_world = im.cam_from_world() * hinge
    # exact synthetic matches: a sound pair is at 1e-6 px, so a tight threshold is safe here
    cons = sequence_consistency(rec, db, names, max_px=0.5, min_matches=20)
    assert [(b.frame_a, b.frame_b) for b in cons.breaks] == [(names[4], names[5])]
    dropped = keep_largest_piece(rec, names, cons)
    assert sorted(dropped) == names[5:]
    assert {im.name for im in rec.images.values() if im.has_pose} == set(names[:5])


def test_consistency_report_round_trips_to_json_types():
    c = Consistency(3, 0.2, 5.0, (Break("a", "b", 80, 5.0),))
    assert not c.ok
    assert c.to_dict()["breaks"] == [{"frames": ["a", "b"], "matches": 80, "median_px": 5.0}]

"""Pose metrics against hand-computed cases (BOP toolkit definitions)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.cad.symmetry import Symmetry, axis_angle_matrix
from cadalign.errors import InputError
from cadalign.geometry.rotations import random_rotation
from cadalign.metrics import pose as pm

SQUARE = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0]])
I3, Z3 = np.eye(3), np.zeros(3)


def rz(deg: float) -> np.ndarray:
    return axis_angle_matrix(np.array([0.0, 0, 1]), math.radians(deg))


def rx(deg: float) -> np.ndarray:
    return axis_angle_matrix(np.array([1.0, 0, 0]), math.radians(deg))


def test_box_iou_hand_case() -> None:
    iou = pm.box_iou(np.array([[0, 0, 2, 2], [0, 0, 0, 0]]), np.array([[1, 1, 3, 3], [0, 0, 2, 2]]))
    np.testing.assert_allclose(iou, [[1 / 7, 1.0], [0.0, 0.0]])


def test_mask_iou_hand_case_and_shape_error() -> None:
    a = np.zeros((4, 4), bool)
    b = np.zeros((4, 4), bool)
    a[:2] = True  # 8 px
    b[1:3] = True  # 8 px, 4 shared
    assert pm.mask_iou(a, b) == pytest.approx(4 / 12)
    assert pm.mask_iou(np.zeros((2, 2), bool), np.zeros((2, 2), bool)) == 0.0
    with pytest.raises(InputError, match="mask shapes differ"):
        pm.mask_iou(a, np.zeros((3, 3), bool))


def test_matching_is_greedy_by_score_and_class_aware() -> None:
    gt = np.array([[0, 0, 10, 10], [20, 0, 30, 10]], float)
    pred = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [20, 0, 30, 10]], float)
    pairs = pm.match_detections(pred, np.array([1, 1, 2]), np.array([0.5, 0.9, 0.8]), gt, np.array([1, 1]))
    # the higher-scoring shifted box takes GT 0; the exact box finds no free GT; class 2 never matches class 1
    assert pairs == [(1, 0)]
    c = pm.DetectionCounts(tp=1, fp=2, fn=1)
    assert (c.precision, c.recall, c.f1) == pytest.approx((1 / 3, 0.5, 0.4))


def test_detection_errors_sort_each_false_positive_and_miss_into_tides_kinds() -> None:
    gt = np.array([[0, 0, 10, 10],      # 0: class 1, hit by pred 0, pred 1 duplicates it
                   [20, 0, 30, 10],     # 1: class 1, only a narrow box on it (IoU 0.3): localization
                   [40, 0, 50, 10],     # 2: class 1, a class-2 box right on it: class error
                   [60, 0, 70, 10],     # 3: class 2, nothing near: missed
                   [80, 0, 90, 10]], float)  # 4: class 1, not counted (don't care), a narrow box on it
    gl = np.array([1, 1, 1, 2, 1])
    pred = np.array([[0, 0, 10, 10], [0, 0, 10, 9], [20, 0, 23, 10], [40, 0, 50, 10], [100, 50, 110, 60],
                     [80, 0, 83, 10], [60, 0, 64, 10]], float)
    pl = np.array([1, 1, 1, 2, 1, 1, 1])  # pred 6: class 1 on the class-2 target at IoU 0.4: both
    scores = np.array([0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3])
    counted = np.array([True, True, True, True, False])
    pairs = pm.match_detections(pred, pl, scores, gt, gl)
    assert pairs == [(0, 0)]
    fe = pm.detection_errors(pred, pl, scores, gt, gl, counted, pairs)
    assert fe.fp_kind == [None, "duplicate", "localization", "class", "background", "localization", "both"]
    assert fe.fn_kind == [None, "localization", "class", "missed", None]
    assert fe.fixed_by == [None, 2, 3, None, None]


def test_detection_errors_pair_localization_errors_one_to_one() -> None:
    """Two narrow boxes on one missed target explain one miss; the better-scoring one is paired, and the other
    is still a localization false positive (fixing it makes a duplicate, which goes)."""
    gt = np.array([[0, 0, 10, 10], [50, 0, 60, 10]], float)
    pred = np.array([[0, 0, 4, 10], [6, 0, 10, 10]], float)  # IoU 0.4 each
    assert pm.match_detections(pred, np.array([1, 1]), np.array([0.2, 0.7]), gt, np.array([1, 1])) == []
    fe = pm.detection_errors(pred, np.array([1, 1]), np.array([0.2, 0.7]), gt, np.array([1, 1]),
                             np.array([True, True]), [])
    assert fe.fp_kind == ["localization", "localization"]
    assert fe.fixed_by == [1, None] and fe.fn_kind == ["localization", "missed"]
    empty = pm.detection_errors(np.zeros((0, 4)), np.zeros(0, int), np.zeros(0), gt, np.array([1, 1]),
                                np.array([True, False]), [])
    assert empty.fp_kind == [] and empty.fn_kind == ["missed", None]
    alone = pm.detection_errors(pred, np.array([1, 1]), np.array([0.2, 0.7]), np.zeros((0, 4)), np.zeros(0, int),
                                np.zeros(0, bool), [])
    assert alone.fp_kind == ["background", "background"] and alone.fn_kind == []


def test_rotation_error_with_and_without_symmetry() -> None:
    assert pm.rotation_error_deg(rz(90), I3) == pytest.approx(90.0)
    cont = Symmetry.continuous([0, 0, 1])
    assert pm.rotation_error_deg(rz(90), I3, cont) == pytest.approx(0.0, abs=1e-7)
    # a tilt of the axis is not hidden by the symmetry, whatever the spin about it
    assert pm.rotation_error_deg(rx(10) @ rz(77), I3, cont) == pytest.approx(10.0)
    z2 = Symmetry.from_name("discrete_z2")
    assert pm.rotation_error_deg(rz(180), I3, z2) == pytest.approx(0.0, abs=1e-6)
    assert pm.rotation_error_deg(rz(170), I3, z2) == pytest.approx(10.0)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), angle=st.floats(0.0, 2 * math.pi), name=st.sampled_from(
    ["continuous_x", "continuous_z", "discrete_z2", "discrete_z4"]))
def test_rotation_error_is_zero_on_the_symmetry_orbit(seed: int, angle: float, name: str) -> None:
    R = random_rotation(np.random.default_rng(seed))
    sym = Symmetry.from_name(name)
    for S in sym.discretize(7):
        assert pm.rotation_error_deg(R @ S[:3, :3], R, sym) < 1e-5
    other = random_rotation(np.random.default_rng(seed + 1))
    assert pm.rotation_error_deg(other, R, sym) <= pm.rotation_error_deg(other, R) + 1e-9


def test_add_and_add_s_with_a_symmetric_object() -> None:
    # the square maps onto itself under a quarter turn: ADD sees sqrt(2) per point, ADD-S sees nothing
    assert pm.add(rz(90), Z3, I3, Z3, SQUARE) == pytest.approx(math.sqrt(2))
    assert pm.add_s(rz(90), Z3, I3, Z3, SQUARE) == pytest.approx(0.0, abs=1e-12)
    t = np.array([0.0, 0.0, 0.01])
    assert pm.add(I3, t, I3, Z3, SQUARE) == pytest.approx(0.01)
    assert pm.add_s(I3, t, I3, Z3, SQUARE) == pytest.approx(0.01)


def test_mssd_and_mspd_hand_cases() -> None:
    z4 = pm.symmetry_transforms(Symmetry.from_name("discrete_z4"))
    none = pm.symmetry_transforms(None)
    assert len(z4) == 4 and len(none) == 1
    assert pm.mssd(rz(90), Z3, I3, Z3, SQUARE, z4) == pytest.approx(0.0, abs=1e-12)
    assert pm.mssd(rz(90), Z3, I3, Z3, SQUARE, none) == pytest.approx(math.sqrt(2))
    t_gt = np.array([0.0, 0.0, 1.0])
    assert pm.mssd(I3, t_gt + [0, 0, 0.02], I3, t_gt, SQUARE, none) == pytest.approx(0.02)
    K = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    pts = np.zeros((1, 3))  # one point on the optical axis at z = 1 m: 1 cm sideways is exactly 1 px
    assert pm.mspd(I3, t_gt + [0.01, 0, 0], I3, t_gt, K, pts, none) == pytest.approx(1.0)


def test_bop_thresholds_and_recall() -> None:
    np.testing.assert_allclose(pm.mssd_thresholds_m(2.0), np.arange(1, 11) * 0.1)
    np.testing.assert_allclose(pm.mspd_thresholds_px(1280), np.arange(1, 11) * 10.0)
    np.testing.assert_allclose(pm.recall_curve(np.array([0.5, 1.5, np.inf]), 4, np.array([1.0, 2.0])), [0.25, 0.5])
    # BOP's discretisation of a continuous symmetry: ceil(pi / 0.01) rotations
    assert len(pm.symmetry_transforms(Symmetry.continuous([0, 0, 1]))) == 315


def test_error_stats_and_distance_bins() -> None:
    s = pm.error_stats(np.array([1.0, 3.0, np.nan]))
    assert (s["n"], s["min"], s["max"], s["mean"], s["std"]) == (2, 1.0, 3.0, 2.0, 1.0)
    assert pm.error_stats(np.array([]))["n"] == 0
    rows = pm.binned_by({"e": np.array([1.0, 2.0, 3.0])}, np.array([0.5, 1.5, 1.7]), (0.0, 1.0, 2.0, 3.0))
    assert [r["n"] for r in rows] == [1, 2, 0]
    assert rows[1]["e_mean"] == pytest.approx(2.5) and math.isnan(rows[2]["e_mean"])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), density=st.floats(0.0, 1.0))
def test_cropped_mask_round_trip(seed: int, density: float) -> None:
    from cadalign.metrics.pose_eval import CroppedMask

    mask = np.random.default_rng(seed).random((7, 9)) < density * 0.3
    c = CroppedMask.of(mask)
    np.testing.assert_array_equal(c.full(mask.shape), mask)
    assert c.crop.size <= mask.size

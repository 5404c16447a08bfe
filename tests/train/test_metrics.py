"""Segmentation and Eigen depth metrics against hand-computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.errors import InputError
from cadalign.metrics.depth import DepthAccumulator, DepthEvalConfig, depth_errors, frame_depth_errors
from cadalign.metrics.seg import confusion_matrix, seg_metrics


def test_confusion_and_iou_by_hand():
    label = np.array([[0, 0, 1, 1], [2, 2, 255, 1]])
    pred = np.array([[0, 1, 1, 1], [2, 0, 3, 1]])
    cm = confusion_matrix(pred, label, 4)
    # gt 0: pred 0,1 ; gt 1: 1,1,1 ; gt 2: 2,0 ; the 255 pixel is ignored
    assert cm.tolist() == [[1, 1, 0, 0], [0, 3, 0, 0], [1, 0, 1, 0], [0, 0, 0, 0]]
    m = seg_metrics(cm, ["bg", "structure", "valve", "hot_stab"])
    assert m.iou[0] == pytest.approx(1 / 3)  # tp 1, fp 1 (gt 2 -> 0), fn 1 (-> 1)
    assert m.iou[1] == pytest.approx(3 / 4)
    assert m.iou[2] == pytest.approx(1 / 2)
    assert math.isnan(m.iou[3])  # neither labelled nor predicted
    assert m.miou == pytest.approx((1 / 3 + 3 / 4 + 1 / 2) / 3)
    assert m.miou_fg == pytest.approx((3 / 4 + 1 / 2) / 2)
    assert m.pixel_accuracy == pytest.approx(5 / 7) and m.pixels == 7
    assert m.to_json()["iou"]["hot_stab"] is None


def test_predicted_but_absent_class_has_zero_iou():
    m = seg_metrics(confusion_matrix(np.array([1, 1]), np.array([0, 0]), 2), ["bg", "valve"])
    assert m.iou == (0.0, 0.0) and m.pixel_accuracy == 0.0


def test_confusion_rejects_bad_input():
    with pytest.raises(InputError, match="shape"):
        confusion_matrix(np.zeros((2, 2)), np.zeros((2, 3)), 2)
    with pytest.raises(InputError, match=r"\[0, 2\)"):
        confusion_matrix(np.array([2]), np.array([0]), 2)


def test_eigen_metrics_by_hand():
    pred, gt = np.array([1.0, 1.5, 3.0]), np.array([1.0, 1.0, 2.0])
    e = depth_errors(pred, gt)
    assert e["abs_rel"] == pytest.approx((0 + 0.5 + 0.5) / 3)
    assert e["sq_rel"] == pytest.approx((0 + 0.25 / 1 + 1.0 / 2) / 3)
    assert e["rmse"] == pytest.approx(math.sqrt((0 + 0.25 + 1.0) / 3))
    assert e["rmse_log"] == pytest.approx(math.sqrt(2 * math.log(1.5) ** 2 / 3))
    assert e["delta1"] == pytest.approx(1 / 3)  # ratios 1, 1.5, 1.5
    assert e["delta2"] == 1.0 and e["delta3"] == 1.0  # 1.5 < 1.5625


def test_eigen_metrics_symmetric_ratio_and_errors():
    e = depth_errors(np.array([0.6]), np.array([1.0]))  # ratio max(0.6, 1/0.6) = 1.667 in (1.25², 1.25³)
    assert (e["delta1"], e["delta2"], e["delta3"]) == (0.0, 0.0, 1.0)
    assert math.isnan(depth_errors(np.zeros(0), np.zeros(0))["rmse"])
    with pytest.raises(InputError, match="positive"):
        depth_errors(np.array([0.0]), np.array([1.0]))


def test_frame_protocol_cap_crop_alignment():
    gt = np.array([[1.0, 2.0], [0.0, 100.0]])  # 0 invalid, 100 above the cap
    pred = np.array([[2.0, 4.0], [5.0, 5.0]])
    cfg = DepthEvalConfig(max_depth_m=10.0)
    e, n = frame_depth_errors(pred, gt, cfg)
    assert n == 2 and e["abs_rel"] == pytest.approx(1.0)
    e, n = frame_depth_errors(pred, gt, DepthEvalConfig(max_depth_m=10.0, alignment="median"))
    assert e["abs_rel"] == pytest.approx(0.0) and e["delta1"] == 1.0
    e, n = frame_depth_errors(pred, gt, DepthEvalConfig(max_depth_m=10.0, crop=(0.0, 1.0, 0.5, 1.0)))
    assert n == 1 and e["abs_rel"] == pytest.approx(1.0)
    e, n = frame_depth_errors(np.array([[50.0, 0.0]]), np.array([[2.0, 2.0]]), DepthEvalConfig(max_depth_m=4.0))
    assert n == 2 and e["abs_rel"] == pytest.approx(((4 - 2) / 2 + (2 - 1e-3) / 2) / 2)  # clamped into the cap
    assert DepthEvalConfig().protocol()["alignment"] == "none"


def test_accumulator_is_mean_over_frames():
    acc = DepthAccumulator()
    acc.add(depth_errors(np.array([2.0]), np.array([1.0])), 1)
    acc.add(depth_errors(np.array([1.0, 1.0, 1.0]), np.array([1.0, 1.0, 1.0])), 3)
    acc.add({}, 0)
    s = acc.summary()
    assert s["abs_rel"] == pytest.approx(0.5) and s["frames"] == 2 and s["empty_frames"] == 1 and s["pixels"] == 4


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(0.01, 100.0), min_size=1, max_size=20), st.floats(0.1, 10.0))
def test_perfect_and_scaled_predictions(values, k):
    gt = np.array(values)
    e = depth_errors(gt, gt)
    assert e["abs_rel"] == 0 and e["rmse"] == 0 and e["delta1"] == 1.0
    s = depth_errors(gt * k, gt)
    assert s["abs_rel"] == pytest.approx(abs(k - 1), rel=1e-9, abs=1e-12)
    assert s["rmse_log"] == pytest.approx(abs(math.log(k)), rel=1e-9, abs=1e-12)

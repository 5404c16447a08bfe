"""Accuracy measures of generated ground truth against exact truth, on hand cases."""

from __future__ import annotations

import numpy as np
import pytest

from cadalign.metrics.dataset import boundary_offset_px, depth_errors, mask_iou


def _rect(h: int, w: int, grow: int = 0, shape: tuple[int, int] = (200, 200)) -> np.ndarray:
    m = np.zeros(shape, bool)
    m[50 - grow: 50 + h + grow, 50 - grow: 50 + w + grow] = True
    return m


@pytest.mark.parametrize(("h", "w"), [(40, 40), (3, 100), (30, 100)])
def test_an_outline_grown_by_one_pixel_is_one_pixel_off_whatever_the_size(h: int, w: int):
    truth, grown = _rect(h, w), _rect(h, w, grow=1)
    offset, width = boundary_offset_px(truth, grown)
    assert offset == pytest.approx(1.0, rel=0.06)  # the four grown corner pixels add a little
    assert width == pytest.approx(2 * h * w / (2 * (h + w) - 4), rel=1e-9)


def test_thin_parts_lose_iou_but_not_offset():
    thin, thick = _rect(3, 100), _rect(30, 100)
    shift = lambda m: np.roll(m, 1, axis=0)  # noqa: E731  (one pixel across the bars)
    iou_thin, iou_thick = mask_iou(thin, shift(thin)), mask_iou(thick, shift(thick))
    assert iou_thin == pytest.approx(2 / 4) and iou_thick == pytest.approx(29 / 31)
    d_thin, d_thick = boundary_offset_px(thin, shift(thin))[0], boundary_offset_px(thick, shift(thick))[0]
    # the long sides move one pixel, the short ones slide along themselves: 200 px over each outline
    assert d_thin == pytest.approx(200 / 202) and d_thick == pytest.approx(200 / 256)


def test_empty_truth_has_no_offset_and_identical_masks_none():
    assert np.isnan(boundary_offset_px(np.zeros((5, 5), bool), np.ones((5, 5), bool))[0])
    m = _rect(10, 10)
    assert boundary_offset_px(m, m) == (0.0, 2 * 100 / 36)


def test_depth_errors_on_a_hand_case():
    true = np.array([[2.0, 4.0], [0.0, np.nan]])
    pred = np.array([[2.2, 3.0], [1.0, 1.0]])
    e = depth_errors(pred, true)
    assert e["coverage"] == 1.0 and e["n_pixels"] == 2
    assert e["abs_rel"] == pytest.approx((0.1 + 0.25) / 2)
    assert e["rmse_m"] == pytest.approx(np.sqrt((0.04 + 1.0) / 2))
    assert e["delta1"] == pytest.approx(0.5)  # ratios 1.1 and 1.333: only the first is within 1.25

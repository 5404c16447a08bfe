"""RoIAlign, NMS and box coding against reference formulas (hand cases and scalar re-implementations)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.models.ops import _nms_first_kept, batched_nms, box_iou, decode_boxes, encode_boxes, nms, roi_align


def _ref_bilinear(img: np.ndarray, y: float, x: float) -> float:
    """torchvision's CPU ``bilinear_interpolate``, line by line."""
    h, w = img.shape
    if y < -1.0 or y > h or x < -1.0 or x > w:
        return 0.0
    y, x = max(y, 0.0), max(x, 0.0)
    y_low, x_low = int(y), int(x)
    if y_low >= h - 1:
        y_high = y_low = h - 1
        y = float(y_low)
    else:
        y_high = y_low + 1
    if x_low >= w - 1:
        x_high = x_low = w - 1
        x = float(x_low)
    else:
        x_high = x_low + 1
    ly, lx = y - y_low, x - x_low
    hy, hx = 1 - ly, 1 - lx
    return hy * hx * img[y_low, x_low] + hy * lx * img[y_low, x_high] + ly * hx * img[y_high, x_low] + \
        ly * lx * img[y_high, x_high]


def _ref_roi_align(img: np.ndarray, box, out: int, scale: float, ratio: int, aligned: bool) -> np.ndarray:
    """torchvision's CPU ``roi_align_forward`` for one channel and one RoI, as scalar loops."""
    off = 0.5 if aligned else 0.0
    x0, y0 = box[0] * scale - off, box[1] * scale - off
    rw, rh = box[2] * scale - off - x0, box[3] * scale - off - y0
    if not aligned:
        rw, rh = max(rw, 1.0), max(rh, 1.0)
    bh, bw = rh / out, rw / out
    gh = ratio if ratio > 0 else math.ceil(rh / out)
    gw = ratio if ratio > 0 else math.ceil(rw / out)
    count = max(gh * gw, 1)
    res = np.zeros((out, out))
    for ph in range(out):
        for pw in range(out):
            acc = 0.0
            for iy in range(gh):
                y = y0 + ph * bh + (iy + 0.5) * bh / gh
                for ix in range(gw):
                    x = x0 + pw * bw + (ix + 0.5) * bw / gw
                    acc += _ref_bilinear(img, y, x)
            res[ph, pw] = acc / count
    return res


def test_roi_align_linear_ramp_is_exact():
    # f(y, x) = 2x + 3y + 1 sampled at integer indices; bilinear interpolation of a linear function is exact,
    # so each bin is the ramp at the bin centre: x = x1*s - 0.5 + (pw + 0.5) * bin_w (aligned=True).
    h, w = 20, 24
    yy, xx = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    feat = (2 * xx + 3 * yy + 1)[None, None]
    box = torch.tensor([[0, 8.0, 6.0, 30.0, 22.0]], dtype=torch.float64)  # image px, scale 1/2 -> feat px
    out = roi_align(feat, box, 4, spatial_scale=0.5, sampling_ratio=2, aligned=True)[0, 0]
    x0, y0, bw, bh = 4.0 - 0.5, 3.0 - 0.5, 11.0 / 4, 8.0 / 4
    expect = torch.tensor([[2 * (x0 + (j + 0.5) * bw) + 3 * (y0 + (i + 0.5) * bh) + 1 for j in range(4)]
                           for i in range(4)], dtype=torch.float64)
    torch.testing.assert_close(out, expect, rtol=0, atol=1e-12)
    # aligned=False differs by exactly the half-pixel shift: 0.5 * (2 + 3) on the ramp
    out_na = roi_align(feat, box, 4, spatial_scale=0.5, sampling_ratio=2, aligned=False)[0, 0]
    torch.testing.assert_close(out_na - out, torch.full_like(out, 2.5), rtol=0, atol=1e-12)


def test_roi_align_adaptive_grid_and_batch_index():
    feat = torch.arange(2 * 3 * 8 * 8, dtype=torch.float64).reshape(2, 3, 8, 8)
    rois = torch.tensor([[1, 0.0, 0.0, 8.0, 8.0], [0, 2.0, 1.0, 5.0, 7.0]], dtype=torch.float64)
    out = roi_align(feat, rois, 2, sampling_ratio=0, aligned=True)
    for r, (b, *box) in enumerate(rois.tolist()):
        for c in range(3):
            ref = _ref_roi_align(feat[int(b), c].numpy(), box, 2, 1.0, 0, True)
            np.testing.assert_allclose(out[r, c].numpy(), ref, atol=1e-12)


coord = st.floats(-6.0, 22.0, allow_nan=False)


@settings(max_examples=30, deadline=None)
@given(x1=coord, y1=coord, dw=st.floats(0.0, 14.0), dh=st.floats(0.0, 14.0), ratio=st.integers(-1, 3),
       aligned=st.booleans(), scale=st.sampled_from([1.0, 0.5, 0.25]), seed=st.integers(0, 99))
def test_roi_align_matches_reference_kernel(x1, y1, dw, dh, ratio, aligned, scale, seed):
    # boxes partly or fully outside the map, empty boxes, adaptive and fixed grids
    img = np.random.default_rng(seed).normal(size=(7, 9))
    box = [x1, y1, x1 + dw, y1 + dh]
    out = roi_align(torch.from_numpy(img)[None, None], torch.tensor([[0.0, *box]], dtype=torch.float64), 3,
                    spatial_scale=scale, sampling_ratio=ratio, aligned=aligned)
    np.testing.assert_allclose(out[0, 0].numpy(), _ref_roi_align(img, box, 3, scale, ratio, aligned), atol=1e-10)


def test_roi_align_gradcheck_and_empty():
    feat = torch.randn(1, 2, 6, 5, dtype=torch.float64, requires_grad=True)
    rois = torch.tensor([[0, 0.7, 1.2, 4.1, 5.3], [0, -1.0, 2.0, 3.0, 9.0]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda f: roi_align(f, rois, 2, 0.8, 2, True), (feat,))
    assert roi_align(feat, rois[:0], 2).shape == (0, 2, 2, 2)
    with pytest.raises(ValueError, match="rois"):
        roi_align(feat, rois[:, :4], 2)


def _ref_nms(boxes: np.ndarray, scores: np.ndarray, thr: float) -> list[int]:
    def iou(a, b):
        iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
        ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
        inter = iw * ih
        union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
        return inter / union if union > 0 else 0.0

    order = sorted(range(len(scores)), key=lambda i: (-scores[i], i))
    keep: list[int] = []
    for i in order:
        if all(iou(boxes[i], boxes[k]) <= thr for k in keep):
            keep.append(i)
    return keep


@settings(max_examples=40, deadline=None)
@given(n=st.integers(0, 40), seed=st.integers(0, 10_000), thr=st.floats(0.0, 1.0), n_cls=st.integers(1, 3))
def test_nms_matches_brute_force(n, seed, thr, n_cls):
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0, 50, (n, 2))
    wh = rng.uniform(0.5, 30, (n, 2))
    boxes = np.concatenate([xy, xy + wh], 1)
    scores = rng.choice(np.linspace(0, 1, 7), n)  # repeated scores exercise the tie rule
    keep = nms(torch.tensor(boxes), torch.tensor(scores), thr).tolist()
    assert keep == _ref_nms(boxes, scores, thr)
    assert nms(torch.tensor(boxes), torch.tensor(scores), thr, max_keep=3).tolist() == keep[:3]
    cls = rng.integers(0, n_cls, n)
    got = batched_nms(torch.tensor(boxes), torch.tensor(scores), torch.tensor(cls), thr).tolist()
    expect = []
    for c in range(n_cls):
        idx = np.flatnonzero(cls == c)
        expect += [int(idx[k]) for k in _ref_nms(boxes[idx], scores[idx], thr)]
    assert sorted(got) == sorted(expect)
    assert [scores[i] for i in got] == sorted((scores[i] for i in got), reverse=True)


@settings(max_examples=40, deadline=None)
@given(n=st.integers(1, 60), seed=st.integers(0, 10_000), thr=st.floats(0.0, 1.0), block=st.integers(1, 9),
       max_keep=st.integers(1, 70))
def test_nms_first_kept_blocks_match_brute_force(n, seed, thr, block, max_keep):
    """With ``max_keep`` NMS visits boxes block by block; any block size gives greedy NMS's first kept boxes."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0, 40, (4, 2))[rng.integers(0, 4, n)] + rng.normal(0, 3, (n, 2))
    wh = rng.uniform(0.0, 20, (n, 2)) * (rng.random((n, 1)) > 0.1)  # some empty boxes
    boxes = np.concatenate([centres - wh / 2, centres + wh / 2], 1)
    scores = rng.choice(np.linspace(0, 1, 5), n)
    order = np.array(sorted(range(n), key=lambda i: (-scores[i], i)))
    b = boxes[order]
    area = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    got = order[_nms_first_kept(b, area, thr, max_keep, block=block)].tolist()
    assert got == _ref_nms(boxes, scores, thr)[:max_keep]


def test_nms_max_keep_on_proposal_sized_input():
    """RPN-sized input (5000 clustered boxes, 500 kept) takes the block path; it equals the full NMS cut."""
    rng = np.random.default_rng(3)
    n = 5000
    centres = rng.uniform(0, 300, (40, 2))[rng.integers(0, 40, n)] + rng.normal(0, 8, (n, 2))
    wh = rng.uniform(4, 60, (n, 2))
    boxes = torch.tensor(np.concatenate([centres - wh / 2, centres + wh / 2], 1), dtype=torch.float32)
    scores = torch.tensor(rng.normal(size=n).round(1), dtype=torch.float32)
    full = nms(boxes, scores, 0.7, use_accel=False)
    assert len(full) > 1000
    for k in (1, 127, 128, 129, 500, len(full), n):
        assert torch.equal(nms(boxes, scores, 0.7, max_keep=k, use_accel=False), full[:k])


def test_nms_hand_case():
    boxes = torch.tensor([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30], [0, 0, 10, 10.0]])
    scores = torch.tensor([0.9, 0.8, 0.7, 0.95])
    # IoU(0,1) = 81/119 = 0.68: suppressed at 0.5, kept at 0.7; box 3 duplicates box 0 and wins on score
    assert nms(boxes, scores, 0.5).tolist() == [3, 2]
    assert nms(boxes, scores, 0.7).tolist() == [3, 1, 2]
    assert nms(boxes[:0], scores[:0], 0.5).numel() == 0


def test_box_coding_round_trip_and_iou():
    rng = torch.Generator().manual_seed(0)
    p = torch.rand(50, 2, generator=rng, dtype=torch.float64) * 100
    props = torch.cat([p, p + 1 + torch.rand(50, 2, generator=rng, dtype=torch.float64) * 50], 1)
    g = torch.rand(50, 2, generator=rng, dtype=torch.float64) * 100
    gt = torch.cat([g, g + 1 + torch.rand(50, 2, generator=rng, dtype=torch.float64) * 50], 1)
    for w in [(1.0, 1.0, 1.0, 1.0), (10.0, 10.0, 5.0, 5.0)]:
        torch.testing.assert_close(decode_boxes(encode_boxes(gt, props, w), props, w), gt)
    iou = box_iou(torch.tensor([[0, 0, 2, 2.0]]), torch.tensor([[1, 1, 3, 3.0], [5, 5, 5, 5.0]]))
    torch.testing.assert_close(iou, torch.tensor([[1 / 7, 0.0]]))


def test_roi_align_keeps_box_coordinates_precise_for_bf16_features():
    """bf16 features (autocast) must not round the RoI coordinates: on the ramp f = x - 100 a box from 150.3
    to 152.3 samples x = 150.8 (value 50.8, 50.75 in bf16); bf16 coordinates (150, 152) would sample 50.5."""
    ramp = (torch.arange(200, dtype=torch.float32) - 100).expand(1, 1, 4, 200).contiguous()
    rois = torch.tensor([[0, 150.3, 1.0, 152.3, 3.0]])
    out = roi_align(ramp.bfloat16(), rois, 1, 1.0, 1, True, use_accel=False)
    assert out.dtype == torch.bfloat16
    assert abs(float(out) - 50.8) <= 0.06
    assert abs(float(roi_align(ramp, rois, 1, 1.0, 1, True, use_accel=False)) - 50.8) < 1e-4

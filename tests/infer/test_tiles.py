"""Zoomed test-time windows of the network detector: geometry of the windows, the merge, coordinates and K."""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from cadalign.infer.config import InferConfig, TileConfig
from cadalign.infer.detect import TorchDetector, merge_detections, tile_windows
from cadalign.types import Detection


@settings(max_examples=60, deadline=None)
@given(h=st.integers(24, 600), w=st.integers(24, 900), zoom=st.floats(1.05, 4.0), overlap=st.floats(0.0, 0.9))
def test_windows_cover_the_frame_and_overlap(h: int, w: int, zoom: float, overlap: float) -> None:
    cfg = TileConfig(zoom=zoom, overlap=overlap)
    wins = tile_windows(h, w, cfg)
    tw, th = int(round(w / zoom)), int(round(h / zoom))
    if tw < 8 or th < 8:
        assert wins == []
        return
    covered = np.zeros((h, w), bool)
    for x0, y0, ww, hh in wins:
        assert (ww, hh) == (tw, th) and 0 <= x0 <= w - ww and 0 <= y0 <= h - hh
        covered[y0:y0 + hh, x0:x0 + ww] = True
    assert covered.all()
    xs, ys = sorted({x for x, _, _, _ in wins}), sorted({y for _, y, _, _ in wins})
    for a, b in pairwise(xs):  # neighbours share at least `overlap` of a window (1 px rounding)
        assert tw - (b - a) >= overlap * tw - 1
    for a, b in pairwise(ys):
        assert th - (b - a) >= overlap * th - 1


def test_zoom_one_is_off_and_a_default_zoom_gives_four_windows() -> None:
    assert tile_windows(480, 640, TileConfig()) == []
    assert tile_windows(480, 640, TileConfig(zoom=1.6)) == [(0, 0, 400, 300), (240, 0, 400, 300),
                                                             (0, 180, 400, 300), (240, 180, 400, 300)]
    assert InferConfig().tiles.zoom == 1.0  # off unless asked for


def _det(box, label, score) -> Detection:
    return Detection(np.asarray(box, float), label, score, np.zeros((4, 4), bool), np.eye(3), np.zeros(3))


def test_merge_keeps_the_best_of_overlapping_same_class_boxes_only() -> None:
    dets = [_det([0, 0, 10, 10], 2, 0.6), _det([1, 0, 11, 10], 2, 0.9), _det([1, 0, 11, 10], 3, 0.5),
            _det([30, 30, 40, 40], 2, 0.7)]
    kept = merge_detections(dets, 0.5)
    assert [d.score for d in kept] == [0.9, 0.7, 0.5]
    assert len(merge_detections(dets, 0.95)) == 4  # IoU 0.82 stays under a stricter threshold
    assert merge_detections([], 0.5) == []


@dataclass
class _BlobNet:
    """Stands in for ``MaskRCNNPose.detect``: resizes its input to ``input_hw`` like the network, detects bright
    blobs at least ``min_px`` wide there, and reports each blob's centre ray at 1 m through its K (so a window's
    K must be the frame's K moved by the window's offset for the pose to come out right)."""

    input_hw: tuple[int, int] = (120, 160)
    min_px: int = 4

    def detect(self, image: torch.Tensor, K: torch.Tensor, score_thresh: float = 0.5) -> list[Detection]:
        h0, w0 = image.shape[-2:]
        h, w = self.input_hw
        x = F.interpolate(image[None], size=(h, w), mode="bilinear", align_corners=False, antialias=True)[0]
        lab, n = ndimage.label(x.mean(0).numpy() > 0.5)
        sx, sy = w0 / w, h0 / h
        out = []
        for i, sl in enumerate(ndimage.find_objects(lab)):
            if sl is None or min(sl[0].stop - sl[0].start, sl[1].stop - sl[1].start) < self.min_px:
                continue
            box = np.array([sl[1].start * sx, sl[0].start * sy, sl[1].stop * sx, sl[0].stop * sy])
            mask = np.zeros((h0, w0), bool)
            mask[int(round(box[1])):int(round(box[3])), int(round(box[0])):int(round(box[2]))] = True
            u, v = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
            Kn = K.double().numpy()
            t = np.array([(u - Kn[0, 2]) / Kn[0, 0], (v - Kn[1, 2]) / Kn[1, 1], 1.0])
            out.append(Detection(box, 2, 0.9 - 0.01 * i, mask, np.eye(3), t))
        return out


def _frame(squares: list[tuple[int, int, int]]) -> np.ndarray:
    img = np.zeros((120, 160, 3), np.uint8)
    for x, y, s in squares:
        img[y:y + s, x:x + s] = 255
    return img


K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])


def test_windows_find_a_part_too_small_for_the_whole_frame_with_frame_coordinates_and_pose() -> None:
    img = _frame([(100, 30, 3), (20, 70, 10)])  # 3 px: under the stand-in's 4 px at zoom 1, 6 px at zoom 2
    whole = TorchDetector(_BlobNet()).detect(img, K)
    assert [tuple(d.box_xyxy) for d in whole] == [(20, 70, 30, 80)]
    tiled = TorchDetector(_BlobNet(), tiles=TileConfig(zoom=2.0)).detect(img, K)
    boxes = sorted(tuple(np.round(d.box_xyxy, 6)) for d in tiled)
    assert boxes == [(20, 70, 30, 80), (100, 30, 103, 33)]  # the big one once: duplicates merged
    for d in tiled:
        x0, y0, x1, y1 = d.box_xyxy
        assert d.mask.shape == img.shape[:2] and d.mask.sum() == (x1 - x0) * (y1 - y0)
        u, v = (x0 + x1) / 2, (y0 + y1) / 2  # the pose is in the frame's camera
        np.testing.assert_allclose(d.t_cam_from_obj_m, [(u - 80) / 100, (v - 60) / 100, 1.0], atol=1e-9)
    strict = TorchDetector(_BlobNet(), tiles=TileConfig(zoom=2.0, score_thresh=0.95)).detect(img, K)
    assert [tuple(d.box_xyxy) for d in strict] == [(20, 70, 30, 80)]  # windows' detections (0.9) under their bar
    # windows keep only boxes up to max_box_px: the 3 px part stays, the 10 px one is the whole frame's alone
    det = TorchDetector(_BlobNet(), tiles=TileConfig(zoom=2.0, max_box_px=5.0), nms_iou=0.99)
    assert sorted(tuple(np.round(d.box_xyxy, 6)) for d in det.detect(img, K)) == [(20, 70, 30, 80), (100, 30, 103, 33)]
    det = TorchDetector(_BlobNet(), tiles=TileConfig(zoom=2.0, max_box_px=2.0), nms_iou=0.99)
    assert [tuple(d.box_xyxy) for d in det.detect(img, K)] == [(20, 70, 30, 80)]


def test_a_part_cut_by_an_inner_window_edge_is_left_to_another_window() -> None:
    # zoom 2 on 160 x 120: windows 80 x 60 at x0 in {0, 40, 80}; a square across x = 80 is cut in the first
    # window (its right edge is inner), whole in the second
    img = _frame([(74, 10, 12)])
    net = _BlobNet(min_px=1000)  # the whole-frame pass finds nothing ...
    det = TorchDetector(net, tiles=TileConfig(zoom=2.0), nms_iou=0.99)  # no merge: the border rule alone
    det._pass = _windows_only(det, net)  # ... and each window pass uses a normal stand-in
    boxes = [tuple(np.round(d.box_xyxy, 6)) for d in det.detect(img, K)]
    assert boxes and all(b == (74, 10, 86, 22) for b in boxes)  # never the cut piece (74..80)


def _windows_only(det: TorchDetector, whole_net: _BlobNet):
    inner = _BlobNet()
    calls = {"n": 0}

    def run(image: np.ndarray, K_: np.ndarray) -> list[Detection]:
        calls["n"] += 1
        net = whole_net if calls["n"] == 1 else inner
        return net.detect(torch.from_numpy(image.transpose(2, 0, 1).copy()).float() / 255, torch.as_tensor(K_))

    return run


@pytest.mark.parametrize("bad", [{"tiles": {"zoom": 0.5}}, {"tiles": {"overlap": 1.0}}, {"nms_iou": 0.0},
                                 {"tiles": {"score_thresh": 1.5}}])
def test_tile_and_nms_settings_are_bounded(bad: dict) -> None:
    from cadalign.config import from_dict
    from cadalign.errors import ConfigError

    key = next(iter(bad["tiles"])) if "tiles" in bad else "nms_iou"
    with pytest.raises(ConfigError, match=key):
        from_dict(InferConfig, bad, source="test")


def test_a_tighter_nms_drops_overlapping_whole_frame_boxes() -> None:
    class Two:
        def detect(self, image, K, score_thresh=0.5):
            m = np.zeros(image.shape[-2:], bool)
            return [Detection(np.array([10.0, 10, 30, 20]), 3, 0.9, m, np.eye(3), np.ones(3)),
                    Detection(np.array([18.0, 10, 38, 20]), 3, 0.7, m, np.eye(3), np.ones(3))]  # IoU 0.43

    img = np.zeros((60, 80, 3), np.uint8)
    assert len(TorchDetector(Two()).detect(img, K)) == 2
    assert [d.score for d in TorchDetector(Two(), nms_iou=0.3).detect(img, K)] == [0.9]

"""The detector interface of the pose pipeline and the trained-network adapter.

Any object with ``detect(image, K) -> list[Detection-like]`` is a :class:`Detector`: ``image`` is (H, W, 3)
RGB uint8, ``K`` (3, 3); a detection has ``box_xyxy`` (4,) px, ``label`` (class index), ``score``, ``mask``
(H, W) bool, ``R_cam_from_obj`` (3, 3), ``t_cam_from_obj_m`` (3,), and optionally ``obj_id`` (the BOP model)
— the attributes of ``cadalign.models.maskrcnn.detector.Detection``.

The ground-truth oracle, for tests and demos only, is :class:`cadalign.testing.oracle.OracleDetector`.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from cadalign.errors import InputError
from cadalign.formats.bop import BopScene
from cadalign.infer.config import TileConfig
from cadalign.io import read_json

log = logging.getLogger(__name__)


class Detector(Protocol):
    def detect(self, image: np.ndarray, K: np.ndarray) -> list[Any]: ...


def tile_windows(height: int, width: int, cfg: TileConfig) -> list[tuple[int, int, int, int]]:
    """``(x0, y0, w, h)`` windows ``1 / zoom`` of the frame, evenly spread and overlapping by at least
    ``overlap``; empty when ``zoom`` is 1 (or the windows would be under 8 px)."""
    if cfg.zoom <= 1.0:
        return []
    tw, th = int(round(width / cfg.zoom)), int(round(height / cfg.zoom))
    if tw < 8 or th < 8:
        return []

    def starts(full: int, size: int) -> list[int]:
        n = 1 + max(0, int(np.ceil((full - size) / (size * (1.0 - cfg.overlap)) - 1e-9)))
        return sorted({int(round(v)) for v in np.linspace(0, full - size, n)})

    return [(x0, y0, tw, th) for y0 in starts(height, th) for x0 in starts(width, tw)]


def merge_detections(dets: list[Any], iou: float) -> list[Any]:
    """Per-class greedy NMS over detections (any objects with ``box_xyxy``, ``label``, ``score``), by score."""
    if len(dets) <= 1:
        return list(dets)
    import torch  # lazy: heavy dependency (torch)

    from cadalign.models.ops import batched_nms  # lazy: pulls torch

    boxes = torch.as_tensor(np.stack([np.asarray(d.box_xyxy, np.float64) for d in dets]))
    keep = batched_nms(boxes, torch.as_tensor([float(d.score) for d in dets], dtype=torch.float64),
                       torch.as_tensor([int(d.label) for d in dets]), iou)
    return [dets[int(i)] for i in keep]


class TorchDetector:
    """Adapter from a ``MaskRCNNPose`` (tensors in, ``Detection`` out) to the numpy :class:`Detector` protocol.

    ``last_timings`` holds the model's own per-stage seconds when it reports them (``model.last_timings``),
    summed over the passes of ``tiles`` (:class:`TileConfig`). The detections of all passes are non-maximum
    suppressed per class at box IoU ``nms_iou`` (:func:`merge_detections`; at the network's own threshold, 0.5
    unless its config says otherwise, this changes nothing on the whole-frame pass).
    """

    def __init__(self, model: Any, score_thresh: float = 0.5, device: str = "cpu",
                 tiles: TileConfig | None = None, nms_iou: float = 0.5) -> None:
        self.model, self.score_thresh, self.device, self.nms_iou = model, score_thresh, device, nms_iou
        self.tiles = tiles or TileConfig()
        self.last_timings: dict[str, float] = {}

    def _pass(self, image: np.ndarray, K: np.ndarray) -> list[Any]:
        import torch  # lazy: heavy dependency (torch)

        img = torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))).float().div(255.0).to(self.device)
        Kt = torch.as_tensor(np.asarray(K, dtype=np.float32), device=self.device)
        with torch.inference_mode():
            dets = self.model.detect(img, Kt, score_thresh=self.score_thresh)
        for k, v in (getattr(self.model, "last_timings", {}) or {}).items():
            self.last_timings[k] = self.last_timings.get(k, 0.0) + v
        return list(dets)

    def detect(self, image: np.ndarray, K: np.ndarray) -> list[Any]:
        self.last_timings = {}
        dets = self._pass(image, K)
        H, W = image.shape[:2]
        b = self.tiles.border_px
        for x0, y0, tw, th in tile_windows(H, W, self.tiles):
            Kw = np.array(K, dtype=np.float64)
            Kw[0, 2] -= x0
            Kw[1, 2] -= y0
            inner = (x0 > 0, y0 > 0, x0 + tw < W, y0 + th < H)  # left, top, right, bottom edges inside the frame
            for d in self._pass(image[y0:y0 + th, x0:x0 + tw], Kw):
                bx = np.asarray(d.box_xyxy, np.float64)
                cut = (inner[0] and bx[0] < b) or (inner[1] and bx[1] < b) or (inner[2] and bx[2] > tw - b) \
                    or (inner[3] and bx[3] > th - b)
                big = self.tiles.max_box_px > 0 and max(bx[2] - bx[0], bx[3] - bx[1]) > self.tiles.max_box_px
                if cut or big or float(d.score) < self.tiles.score_thresh:
                    continue
                mask = np.zeros((H, W), dtype=bool)
                mask[y0:y0 + th, x0:x0 + tw] = d.mask
                dets.append(replace(d, box_xyxy=bx + [x0, y0, x0, y0], mask=mask))
        return merge_detections(dets, self.nms_iou)


def frame_ids(scene_dir: Path) -> dict[str, int]:
    """Frame name -> BOP image id of a scene: ``frame_names.json`` (dataset builder) or ``NNNNNN.png``."""

    scene_dir = Path(scene_dir)
    names = scene_dir / "frame_names.json"
    if names.is_file():
        return {str(v): int(k) for k, v in read_json(names).items()}
    return {f"{i:06d}.png": i for i in BopScene(scene_dir).ids}


def resolve_scene_dir(path: Path) -> Path:
    """A BOP scene folder from a simulation folder (``gt/sim/000000``), a built dataset or the scene itself."""
    path = Path(path)
    for cand in (path, path / "gt" / "sim" / "000000", path / "dataset" / "all" / "000000", path / "all" / "000000"):
        if (cand / "scene_gt.json").is_file():
            return cand

    raise InputError(f"{path} holds no BOP scene (looked for scene_gt.json in it, gt/sim/000000, "
                     "dataset/all/000000); pass a 'cadalign sim' output folder or a BOP scene folder")


def models_dir_of(scene_dir: Path) -> Path:
    """The BOP ``models/`` folder that belongs to a scene folder (``../../models``)."""
    return Path(scene_dir).parent.parent / "models"

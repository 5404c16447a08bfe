"""Which frames a dense model trains and evaluates on, at which resolution.

``DS`` is either a dataset root with ``splits.json`` (its ``scene`` and per-split ids: train on ``train``,
evaluate on ``val``/``test``) or a bare BOP scene folder (``all/000000`` of a dataset, ``gt/sim/000000`` of
the simulator); a bare scene is split by :func:`cadalign.formats.splits.time_block_splits` with blocks of
``max(1, min(10, n // 10))`` frames (gap 1 when blocks have more than 2 frames, seed 0), so train and eval
agree on the held-out frames without a file. ``all`` selects every frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch.nn.functional as F
from torch.utils.data import Dataset

from cadalign.errors import InputError
from cadalign.formats.bop import BopScene
from cadalign.formats.splits import SPLITS, time_block_splits
from cadalign.io import read_json
from cadalign.train.datasets import SegmentationDataset

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DataSelection:
    scene_dir: Path
    """The BOP scene folder (rgb/, depth/, class/, objects.json …)."""
    ids: tuple[int, ...]
    """Image ids of the split."""
    split: str
    """The split name (train, val, test or all)."""
    source: str
    """Where the split came from: the splits.json path or the derived time-block split."""


def _scene_ids(scene_dir: Path) -> list[int]:
    return list(BopScene(scene_dir).ids)


def select(ds: Path, split: str) -> DataSelection:
    """The scene folder and the image ids of ``split`` for a dataset root or a bare BOP scene.

    Raises:
        InputError: ``ds`` is neither, the split is unknown, or it holds no frame.
    """
    ds = Path(ds)
    if split not in (*SPLITS, "all"):
        raise InputError(f"unknown split {split!r}; use one of {', '.join((*SPLITS, 'all'))}")
    if (ds / "splits.json").is_file():
        spec = read_json(ds / "splits.json")
        scene = ds / spec.get("scene", "all/000000")
        ids = _scene_ids(scene) if split == "all" else [int(i) for i in spec.get(split, [])]
        source = str(ds / "splits.json")
    elif (ds / "scene_camera.json").is_file() or (ds / "rgb").is_dir():
        scene = ds
        all_ids = _scene_ids(ds)
        n = len(all_ids)
        block = max(1, min(10, n // 10))
        parts = time_block_splits(all_ids, block=block, gap=1 if block > 2 else 0, seed=0)
        ids = all_ids if split == "all" else parts[split]
        source = f"time blocks of {block} frames over the scene's {n} frames (no splits.json)"
    else:
        raise InputError(f"{ds} is neither a dataset root (with splits.json) nor a BOP scene folder (with rgb/); "
                         "pass e.g. OUT/dataset or OUT/dataset/all/000000")
    if not ids:
        raise InputError(f"split '{split}' of {ds} holds no frame ({source}); use --split all or a larger dataset")
    return DataSelection(scene, tuple(ids), split, source)


def resized_size(h: int, w: int, scale: float) -> tuple[int, int]:
    """The (height, width) of an image of (h, w) at ``scale`` (at least 8 px each)."""
    return max(int(round(h * scale)), 8), max(int(round(w * scale)), 8)


class ScaledDataset(Dataset):
    """A dense dataset at ``scale`` with items cached in memory after their first read.

    The image is resized with antialiased bilinear filtering; ``label``, ``depth`` and ``valid`` with nearest
    neighbour (no blended classes or depths across edges). With ``with_fg`` a ``fg`` (1,H,W) float mask of
    non-background pixels is added from the scene's class map (for depth models with a mask input).
    """

    def __init__(self, base: Dataset, scale: float, *, with_fg: bool = False, cache: bool = True) -> None:
        self.base, self.scale, self.with_fg, self.cache = base, scale, with_fg, cache
        self._items: dict[int, dict] = {}
        self._labels = None
        if with_fg:
            self._labels = SegmentationDataset(base.scene.dir, base.ids)

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, i: int) -> dict:
        if i in self._items:
            return self._items[i]
        item = dict(self.base[i])
        if self._labels is not None:
            item["fg"] = (self._labels[i]["label"] > 0).float()[None]
        item = scale_item(item, self.scale)
        if self.cache:
            self._items[i] = item
        return item


def scale_item(item: dict, scale: float) -> dict:
    """Resize the dense tensors of one item (see :class:`ScaledDataset`); other keys pass through."""
    if scale == 1.0:
        return item
    h, w = item["image"].shape[-2:]
    size = resized_size(h, w, scale)
    out = dict(item)
    out["image"] = F.interpolate(item["image"][None], size=size, mode="bilinear", antialias=True,
                                 align_corners=False)[0].clamp(0, 1)
    for k in ("label", "depth", "fg"):
        if k in item:
            t = item[k]
            t2 = t[None, None] if t.ndim == 2 else t[None]
            r = F.interpolate(t2.float(), size=size, mode="nearest")[0]
            out[k] = (r[0] if t.ndim == 2 else r).to(t.dtype)
    if "depth" in item:
        out["valid"] = out["depth"] > 0
    return out


def class_pixel_counts(ds: Dataset, n_classes: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-class pixel counts and pixels of the images containing each class, over a segmentation dataset."""
    counts = np.zeros(n_classes, dtype=np.int64)
    image_counts = np.zeros(n_classes, dtype=np.int64)
    for i in range(len(ds)):
        lab = ds[i]["label"].numpy()
        c = np.bincount(lab[lab < n_classes].ravel(), minlength=n_classes)[:n_classes]
        counts += c
        image_counts += np.where(c > 0, lab.size, 0)
    return counts, image_counts


def depth_percentiles(ds: Dataset, q: tuple[float, float] = (1.0, 99.0), max_items: int = 64) -> tuple[float, float]:
    """Percentiles of the valid depths (metres) of up to ``max_items`` evenly spaced items."""
    idx = np.unique(np.linspace(0, len(ds) - 1, min(len(ds), max_items)).round().astype(int))
    vals = [ds[int(i)]["depth"][ds[int(i)]["valid"]].numpy() for i in idx]
    allv = np.concatenate(vals) if vals else np.zeros(0)
    if allv.size == 0:
        raise InputError("the training frames have no valid depth pixel; check the dataset's depth/ folder")
    lo, hi = np.percentile(allv, q)
    return float(lo), float(hi)

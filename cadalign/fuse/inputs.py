"""Where fusion frames come from: a simulator output or a built dataset, with GT or predicted depth/labels.

Accepted sources (the BOP scene inside is found automatically):

- ``SIM_DIR`` (``cadalign sim``): ``SIM_DIR/gt/sim/000000``
- a build folder (``cadalign build-dataset --out OUT``): ``OUT/dataset/all/000000``
- a dataset folder: ``DS/all/000000``
- a BOP scene folder itself (holding ``scene_camera.json``), also a plain one with only ``rgb/``, ``depth/``,
  ``scene_camera.json`` and ``scene_gt.json``: its classes are one per object id, or a ``classes`` JSON
  ``{obj_id: class name}`` (:func:`cadalign.train.datasets.load_class_map`)

Depth: ``gt`` (the scene's ``depth/``), ``sfm`` (``depth_sfm/`` of a built dataset: sparse, metres after
alignment) or ``pred`` (a :data:`DepthPredictor`). Labels: ``gt`` (``class/``, or painted from the visible
masks) or ``pred`` (a :data:`SegPredictor`). Poses and intrinsics always come from ``scene_camera.json``.

A scene with neither ``class/`` nor ``mask_visib/`` has no ground-truth labels: ``labels="gt"`` then fuses
geometry only (every frame votes uniformly over the classes, so the map's labels carry no information and the
report says ``labels: none``); pass ``labels="pred"`` with a segmentation model for a labelled map.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from cadalign.errors import InputError
from cadalign.formats import bop
from cadalign.formats.class_map import ClassMap, load_class_map
from cadalign.fuse.base import FuseFrame
from cadalign.fuse.semantic import check_probs, probs_from_labels
from cadalign.io import read_image, read_json
from cadalign.types import Camera

log = logging.getLogger(__name__)
DepthSource = Literal["gt", "pred", "sfm"]
LabelSource = Literal["gt", "pred"]
DepthPredictor = Callable[[np.ndarray, Camera], np.ndarray]
"""``(rgb (H, W, 3) uint8, camera) -> (H, W) metric depth``, 0 = invalid."""
SegPredictor = Callable[[np.ndarray], np.ndarray]
"""``rgb (H, W, 3) uint8 -> (C, H, W)`` class probabilities."""


def find_scene(source: Path) -> Path:
    """The BOP scene folder inside a sim output, build output, dataset or scene folder."""
    source = Path(source)
    for rel in (Path("."), Path("gt/sim/000000"), Path("dataset/all/000000"), Path("all/000000")):
        if (source / rel / "scene_camera.json").is_file():
            return (source / rel).resolve()
    raise InputError(f"{source} holds no BOP scene: expected a cadalign sim output (gt/sim/000000), a built "
                     "dataset (dataset/all/000000 or all/000000) or a BOP scene folder with scene_camera.json")


@dataclass(frozen=True)
class FrameSource:
    """Frames of one BOP scene with the chosen depth and label sources."""

    scene: bop.BopScene
    classes: ClassMap
    ids: tuple[int, ...]
    depth: DepthSource = "gt"
    labels: LabelSource = "gt"
    label_confidence: float = 0.95
    depth_predictor: DepthPredictor | None = None
    seg_predictor: SegPredictor | None = None

    @property
    def n_classes(self) -> int:
        return len(self.classes.names)

    @property
    def has_label_truth(self) -> bool:
        """Whether the scene has ground-truth labels (``class/`` or visible masks ``mask_visib/``)."""
        return (self.scene.dir / "class").is_dir() or (self.scene.dir / "mask_visib").is_dir()

    @property
    def labels_used(self) -> str:
        """What labels the map is fused from: 'gt', 'pred', or 'none' (geometry only: no label truth)."""
        return "gt" if self.labels == "gt" and self.has_label_truth else "pred" if self.labels == "pred" else "none"

    def __len__(self) -> int:
        return len(self.ids)

    def frame(self, im_id: int) -> FuseFrame:
        meta = self.scene.frame(im_id)
        if meta.T_cam_from_world is None:
            raise InputError(f"{self.scene.dir}/scene_camera.json: image {im_id} has no camera pose "
                             "(cam_R_w2c/cam_t_w2c); fusion needs posed frames")
        rgb = self.scene.rgb(im_id)
        cam = meta.camera
        return FuseFrame(self._depth(im_id, rgb, cam), self._probs(im_id, rgb), cam, meta.T_cam_from_world, rgb)

    def _depth(self, im_id: int, rgb: np.ndarray, cam: Camera) -> np.ndarray:
        if self.depth == "gt":
            return self.scene.depth_m(im_id)
        if self.depth == "sfm":
            path = self.scene.dir / "depth_sfm" / bop.frame_name(im_id)
            if not path.is_file():
                raise InputError(f"{path} is missing: --depth sfm needs a dataset built by `cadalign build-dataset` "
                                 "(it writes depth_sfm/); use --depth gt or pred for a simulator output")
            return bop.decode_depth(read_image(path, unchanged=True), self.scene.frame(im_id).depth_scale)
        if self.depth_predictor is None:
            raise InputError("--depth pred needs a depth model: pass --model-depth RUN (a `cadalign train depth` run)")
        depth = np.asarray(self.depth_predictor(rgb, cam), dtype=np.float32)
        if depth.shape != (cam.height, cam.width):
            raise InputError(f"the depth model returned shape {depth.shape}; expected ({cam.height}, {cam.width})")
        return depth

    def _probs(self, im_id: int, rgb: np.ndarray) -> np.ndarray:
        h, w = rgb.shape[:2]
        if self.labels == "pred":
            if self.seg_predictor is None:
                raise InputError("--labels pred needs a segmentation model: pass --model-seg RUN "
                                 "(a `cadalign train seg` run)")
            return check_probs(self.seg_predictor(rgb), self.n_classes, (h, w))
        if not self.has_label_truth:  # geometry only: no evidence for any class
            return np.full((self.n_classes, h, w), 1.0 / self.n_classes, dtype=np.float32)
        return probs_from_labels(self.label_map(im_id), self.n_classes, self.label_confidence)

    def label_map(self, im_id: int) -> np.ndarray:
        """(H, W) ground-truth class indices: ``class/`` if present, else painted from the visible masks."""
        png = self.scene.dir / "class" / bop.frame_name(im_id)
        if png.is_file():
            return read_image(png, unchanged=True).astype(np.int64)
        meta = self.scene.frame(im_id)
        label = np.zeros((meta.camera.height, meta.camera.width), dtype=np.int64)
        for g, inst in enumerate(meta.instances):
            label[self.scene.mask(im_id, g, visible=True)] = self.classes.class_of_obj[inst.obj_id]
        return label

    def __iter__(self) -> Iterator[FuseFrame]:
        for im_id in self.ids:
            yield self.frame(im_id)


def split_ids(scene_dir: Path, split: str | None) -> list[int] | None:
    """Image ids of a split from the dataset's ``splits.json`` (two levels above the scene), or None for all."""
    if split is None:
        return None
    path = Path(scene_dir).parents[1] / "splits.json"
    if not path.is_file():
        raise InputError(f"--split {split}: {path} is missing (only built datasets have splits); drop --split")
    splits = read_json(path)
    if split not in splits or not isinstance(splits[split], list):
        allowed = sorted(k for k, v in splits.items() if isinstance(v, list))
        raise InputError(f"{path} has no split {split!r}; allowed: {', '.join(allowed)}")
    return [int(i) for i in splits[split]]


def open_source(source: Path, *, depth: DepthSource = "gt", labels: LabelSource = "gt",
                label_confidence: float = 0.95, split: str | None = None, max_frames: int | None = None,
                id_range: tuple[int, int] | None = None,
                depth_predictor: DepthPredictor | None = None,
                seg_predictor: SegPredictor | None = None, classes: Path | None = None) -> FrameSource:
    """A :class:`FrameSource` over the scene found in ``source`` (see the module docstring)."""
    if depth not in ("gt", "pred", "sfm"):
        raise InputError(f"unknown depth source {depth!r}; allowed: gt, pred, sfm")
    if labels not in ("gt", "pred"):
        raise InputError(f"unknown label source {labels!r}; allowed: gt, pred")
    scene_dir = find_scene(source)
    scene = bop.BopScene(scene_dir)
    ids = split_ids(scene_dir, split) or scene.ids
    if id_range is not None:
        ids = [i for i in ids if id_range[0] <= i < id_range[1]]
    if max_frames is not None:
        ids = ids[:max_frames]
    if not ids:
        raise InputError(f"{scene_dir} has no frames to fuse")
    src = FrameSource(scene, load_class_map(scene_dir, classes), tuple(ids), depth, labels, label_confidence,
                      depth_predictor, seg_predictor)
    if labels == "gt" and not src.has_label_truth:
        log.warning("%s has no ground-truth labels (no class/ or mask_visib/): fusing geometry only; pass "
                    "--labels pred --model-seg RUN for a labelled map", scene_dir)
    return src

"""Torch ``Dataset``s over a BOP scene: segmentation, depth, and detection + pose.

Items are dicts of tensors with documented keys (the one place dicts stand in for dataclasses):
images are float32 (3, H, W) in [0, 1]; depth is metres with 0 = invalid; poses are object-in-camera
in metres. The class map comes from the scene's ``objects.json`` (written by ``cadalign sim`` and
``cadalign build-dataset``): class names, and each BOP ``obj_id``'s class index; a plain BOP scene (``rgb/``,
``depth/``, ``scene_camera.json``, ``scene_gt.json``) gets one class per object id (:func:`load_class_map`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from cadalign.errors import InputError
from cadalign.formats.bop import BopScene, mask_bbox
from cadalign.formats.class_map import ClassMap, load_class_map
from cadalign.io import read_image


def _image(scene: BopScene, im_id: int) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(scene.rgb(im_id).transpose(2, 0, 1))).float() / 255.0


def _label_map(scene: BopScene, im_id: int, classes: ClassMap) -> np.ndarray:
    """(H, W) class indices: the extras' ``class/`` PNG if present, else painted from the visible masks."""
    png = scene.dir / "class" / f"{im_id:06d}.png"
    if png.is_file():
        return read_image(png, unchanged=True).astype(np.int64)
    frame = scene.frame(im_id)
    if frame.instances and not (scene.dir / "mask_visib").is_dir():
        raise InputError(f"{scene.dir} has no ground-truth labels (neither class/ nor mask_visib/, as in a plain BOP "
                         "scene): segmentation needs them; add the BOP visible masks (mask_visib/) or use a dataset "
                         "built by 'cadalign build-dataset'")
    label = np.zeros((frame.camera.height, frame.camera.width), dtype=np.int64)
    for g, inst in enumerate(frame.instances):
        label[scene.mask(im_id, g, visible=True)] = classes.class_of_obj[inst.obj_id]
    return label


class _BopDataset(Dataset):
    def __init__(self, scene_dir: Path, ids: Sequence[int] | None = None) -> None:
        self.scene = BopScene(scene_dir)
        self.ids = list(self.scene.ids if ids is None else ids)
        self.classes = load_class_map(scene_dir)

    def __len__(self) -> int:
        return len(self.ids)

    def image(self, i: int) -> torch.Tensor:
        """``(3, H, W)`` float in [0, 1]: item ``i``'s image alone (no targets read)."""
        return _image(self.scene, self.ids[i])


class SegmentationDataset(_BopDataset):
    """``{"image": (3,H,W) float, "label": (H,W) int64 class index, "im_id": int}``."""

    def __getitem__(self, i: int) -> dict:
        im_id = self.ids[i]
        label = _label_map(self.scene, im_id, self.classes)
        return {"image": _image(self.scene, im_id), "label": torch.from_numpy(label), "im_id": im_id}


class DepthDataset(_BopDataset):
    """``{"image", "depth": (1,H,W) metres (0 = invalid), "valid": (1,H,W) bool, "K": (3,3), "im_id"}``."""

    def __getitem__(self, i: int) -> dict:
        im_id = self.ids[i]
        depth = torch.from_numpy(self.scene.depth_m(im_id).astype(np.float32))[None]
        K = torch.from_numpy(self.scene.frame(im_id).camera.K.astype(np.float32))
        return {"image": _image(self.scene, im_id), "depth": depth, "valid": depth > 0, "K": K, "im_id": im_id}


class DetectionPoseDataset(_BopDataset):
    """Instances with visible pixels: ``{"image", "boxes": (N,4) xyxy px, "labels": (N,) class,
    "obj_ids": (N,), "masks": (N,H,W) bool, "R": (N,3,3), "t": (N,3) metres, "K": (3,3), "im_id"}``."""

    def __getitem__(self, i: int) -> dict:
        im_id = self.ids[i]
        frame = self.scene.frame(im_id)
        masks, boxes, labels, obj_ids, Rs, ts = [], [], [], [], [], []
        for g, inst in enumerate(frame.instances):
            m = self.scene.mask(im_id, g, visible=True)
            if not m.any():
                continue
            x, y, w, h = mask_bbox(m)
            boxes.append([x, y, x + w, y + h])
            masks.append(m)
            labels.append(self.classes.class_of_obj[inst.obj_id])
            obj_ids.append(inst.obj_id)
            Rs.append(inst.T_cam_from_obj.R)
            ts.append(inst.T_cam_from_obj.t)
        h, w = frame.camera.height, frame.camera.width
        return {
            "image": _image(self.scene, im_id),
            "boxes": torch.tensor(np.array(boxes, dtype=np.float32).reshape(-1, 4)),
            "labels": torch.tensor(labels, dtype=torch.int64),
            "obj_ids": torch.tensor(obj_ids, dtype=torch.int64),
            "masks": torch.from_numpy(np.array(masks, dtype=bool).reshape(-1, h, w)),
            "R": torch.tensor(np.array(Rs, dtype=np.float32).reshape(-1, 3, 3)),
            "t": torch.tensor(np.array(ts, dtype=np.float32).reshape(-1, 3)),
            "K": torch.from_numpy(frame.camera.K.astype(np.float32)),
            "im_id": im_id,
        }


def detection_collate(batch: list[dict]) -> dict:
    """Stack images (same size) and keep the per-image instance tensors as lists."""
    out = {"image": torch.stack([b["image"] for b in batch])}
    for key in batch[0]:
        if key != "image":
            out[key] = [b[key] for b in batch]
    return out

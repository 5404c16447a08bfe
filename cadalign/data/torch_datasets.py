"""Torch ``Dataset``s over a BOP scene: segmentation, depth, and detection + pose.

Items are dicts of tensors with documented keys (the one place dicts stand in for dataclasses):
images are float32 (3, H, W) in [0, 1]; depth is metres with 0 = invalid; poses are object-in-camera
in metres. The class map comes from the scene's ``objects.json`` (written by ``cadalign sim`` and
``cadalign build-dataset``): class names, and each BOP ``obj_id``'s class index; a plain BOP scene (``rgb/``,
``depth/``, ``scene_camera.json``, ``scene_gt.json``) gets one class per object id (:func:`load_class_map`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from cadalign.data.bop import BopScene, mask_bbox
from cadalign.errors import InputError
from cadalign.io import read_json


@dataclass(frozen=True)
class ClassMap:
    names: tuple[str, ...]
    """Class names; index 0 is background."""
    class_of_obj: dict[int, int]
    """BOP obj_id -> class index."""


def load_class_map(scene_dir: Path, classes: Path | None = None) -> ClassMap:
    """The class names and obj_id -> class map of a BOP scene, from (first found):

    - ``classes``: a JSON ``{obj_id: class name}`` (objects of one name share a class; "background" is 0);
    - ``scene_dir/objects.json`` (written by ``cadalign sim`` and ``cadalign build-dataset``);
    - a plain BOP scene: one class per object id of ``scene_gt.json``, named ``obj_000001`` ...

    Raises:
        InputError: an unreadable classes file, one that misses object ids of the scene, or a scene with neither
            objects.json nor scene_gt.json.
    """
    scene_dir = Path(scene_dir)
    if classes is not None:
        return _class_map_file(Path(classes), _scene_obj_ids(scene_dir))
    path = scene_dir / "objects.json"
    if path.is_file():
        data = read_json(path)
        return ClassMap(tuple(data["classes"]), {int(o["obj_id"]): int(o["class_id"]) for o in data["objects"]})
    ids = _scene_obj_ids(scene_dir)
    if ids is None:
        raise InputError(f"{scene_dir} has no class map: neither objects.json nor scene_gt.json; pass a classes "
                         "file (JSON {obj_id: class name}) or re-run the stage that wrote the scene")
    return ClassMap(("background", *(f"obj_{i:06d}" for i in ids)), {i: k + 1 for k, i in enumerate(ids)})


def _scene_obj_ids(scene_dir: Path) -> list[int] | None:
    """Sorted object ids of ``scene_gt.json``, or None without one."""
    path = scene_dir / "scene_gt.json"
    if not path.is_file():
        return None
    data = read_json(path)
    return sorted({int(g["obj_id"]) for gts in data.values() for g in gts})


def _class_map_file(path: Path, scene_ids: list[int] | None) -> ClassMap:
    data = read_json(path)
    if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
        raise InputError(f"{path}: a classes file is a JSON object {{obj_id: class name}}, e.g. "
                         '{"1": "valve", "2": "structure"}; fix it')
    try:
        named = {int(k): v for k, v in data.items()}
    except ValueError:
        raise InputError(f"{path}: keys must be BOP object ids (integers), got {sorted(data)[:5]}; fix it") from None
    missing = sorted(set(scene_ids or []) - set(named))
    if missing:
        raise InputError(f"{path} names no class for object ids {missing[:10]} of the scene; add them "
                         '(e.g. "background" for objects to ignore)')
    names = ["background"]
    for oid in sorted(named):
        if named[oid] not in names:
            names.append(named[oid])
    return ClassMap(tuple(names), {oid: names.index(c) for oid, c in named.items()})


def _image(scene: BopScene, im_id: int) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(scene.rgb(im_id).transpose(2, 0, 1))).float() / 255.0


def _label_map(scene: BopScene, im_id: int, classes: ClassMap) -> np.ndarray:
    """(H, W) class indices: the extras' ``class/`` PNG if present, else painted from the visible masks."""
    png = scene.dir / "class" / f"{im_id:06d}.png"
    if png.is_file():
        from cadalign.io import read_image

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

"""COCO-style instance annotations (boxes, uncompressed RLE masks) for a BOP scene.

Pure numpy: no pycocotools needed. RLE follows COCO's convention: run lengths over the mask in
column-major (Fortran) order, starting with a run of zeros.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from cadalign.formats.bop import BopScene, frame_name, mask_bbox
from cadalign.io import write_json


def mask_to_rle(mask: np.ndarray) -> dict:
    """``{"size": [H, W], "counts": [...]}`` of a boolean (H, W) mask, column-major runs from zero."""
    flat = np.asarray(mask, dtype=bool).ravel(order="F")
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    edges = np.concatenate([[0], change, [flat.size]])
    counts = np.diff(edges).tolist()
    if flat.size and flat[0]:
        counts = [0, *counts]
    return {"size": [int(mask.shape[0]), int(mask.shape[1])], "counts": [int(c) for c in counts]}


def rle_to_mask(rle: dict) -> np.ndarray:
    """Inverse of :func:`mask_to_rle`."""
    h, w = rle["size"]
    values = np.arange(len(rle["counts"])) % 2 == 1
    flat = np.repeat(values, rle["counts"])
    return flat.reshape((h, w), order="F")


def coco_annotations(scene: BopScene, ids: Sequence[int], class_of_obj: dict[int, int],
                     class_names: Sequence[str],
                     visible_masks: Callable[[int, int], Sequence[np.ndarray]] | None = None) -> dict:
    """COCO dict (images, annotations, categories) for frames ``ids`` from their visible masks.

    ``category_id`` is the class index (1.. for foreground classes); each annotation also keeps the
    BOP ``obj_id`` and ``gt_idx`` so the pose can be looked up in ``scene_gt.json``. ``visible_masks``:
    ``(im_id, n_instances) -> `` the frame's (H, W) bool visible masks by gt index, when the caller has them
    cheaper than the ``mask_visib`` PNGs (default: those PNGs).
    """
    images, anns = [], []
    for im_id in ids:
        frame = scene.frame(im_id)
        images.append({"id": int(im_id), "file_name": f"rgb/{frame_name(im_id)}",
                       "width": frame.camera.width, "height": frame.camera.height})
        masks = visible_masks(im_id, len(frame.instances)) if visible_masks is not None else None
        for g, inst in enumerate(frame.instances):
            mask = masks[g] if masks is not None else scene.mask(im_id, g, visible=True)
            area = int(mask.sum())
            if area == 0:
                continue
            anns.append({
                "id": len(anns) + 1, "image_id": int(im_id), "category_id": int(class_of_obj[inst.obj_id]),
                "bbox": mask_bbox(mask),
                "area": area, "iscrowd": 0, "segmentation": mask_to_rle(mask),
                "obj_id": inst.obj_id, "gt_idx": g,
            })
    cats = [{"id": i, "name": n} for i, n in enumerate(class_names) if i > 0]
    return {"images": images, "annotations": anns, "categories": cats}


def write_coco(path: Path, coco: dict) -> Path:
    return write_json(path, coco, indent=None)

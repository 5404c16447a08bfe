"""Write ray-cast ground truth as a BOP scene, one frame at a time, resumably.

Shared by the simulator (true cameras) and the dataset builder (SfM cameras, aligned CAD). Each frame's
files are written in place and then a small record ``frames_json/NNNNNN.json`` is written atomically,
last: a frame counts as done only when its record exists, so an interrupted run redoes only the frame
it was writing. :func:`merge_scene_files` turns the records into the BOP scene JSONs.

Extras beyond BOP (documented in the README): ``class/`` (uint8 class index per pixel), ``instance/``
(uint16; 0 = none, g = GT instance g-1 of the frame), ``normals/`` (npz float16, camera frame),
``cameras.json`` (per frame ``T_cam_from_world`` in metres and K) and ``objects.json`` (classes and each
instance's model id, class and world pose).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cadalign.formats import bop
from cadalign.formats.tum import TUM_NAME, write_cameras_tum
from cadalign.io import atomic_path, link_or_copy, read_image, read_json, write_image, write_json
from cadalign.raycast.core import RaycastFrame
from cadalign.types import Camera, Rigid3


@dataclass(frozen=True)
class PosedObject:
    """An object instance of the structure: ray-cast instance id ``index + 1``."""

    name: str
    obj_id: int
    """BOP model id (instances of one model share it)."""
    class_id: int
    T_world_from_obj: Rigid3


def frame_done(scene_dir: Path, k: int) -> bool:
    """Whether frame ``k`` was completely written (its record exists)."""
    return (Path(scene_dir) / "frames_json" / f"{k:06d}.json").is_file()


def write_bop_frame(scene_dir: Path, k: int, camera: Camera, T_cam_from_world: Rigid3, gt: RaycastFrame,
                    objects: Sequence[PosedObject], depth_scale: float, *, rgb: np.ndarray | None = None,
                    rgb_source: Path | None = None) -> None:
    """Write frame ``k``: rgb (from an array, or a hard link/copy of ``rgb_source``), depth, masks, extras.

    ``gt.instance`` / ``gt.full_masks`` use instance id ``i + 1`` for ``objects[i]``.
    """
    sdir = Path(scene_dir)
    name = bop.frame_name(k)
    if rgb is not None:
        write_image(sdir / "rgb" / name, rgb, atomic=False)
    elif rgb_source is not None:
        link_or_copy(Path(rgb_source), sdir / "rgb" / name)
    visible = sorted(gt.full_masks)
    fulls = [gt.full_masks[i] for i in visible]
    visibs = [gt.instance == i for i in visible]
    bop.write_frame_gt(sdir, k, gt.depth_m, depth_scale, fulls, visibs, atomic=False)
    write_image(sdir / "class" / name, gt.class_id.astype(np.uint8), atomic=False)
    inst = np.zeros(gt.instance.shape, dtype=np.uint16)
    for g, i in enumerate(visible):
        inst[gt.instance == i] = g + 1
    write_image(sdir / "instance" / name, inst, atomic=False)
    save_npz(sdir / "normals" / f"{k:06d}.npz", normals=gt.normals_cam.astype(np.float16))
    record = {
        "camera": bop.camera_entry(camera, T_cam_from_world, depth_scale),
        "gt": [
            bop.gt_entry(bop.BopInstance(objects[i - 1].obj_id, T_cam_from_world @ objects[i - 1].T_world_from_obj))
            for i in visible
        ],
        "gt_info": [bop.gt_info_entry(f, v, gt.depth_m > 0) for f, v in zip(fulls, visibs, strict=True)],
        "object_index": [i - 1 for i in visible],
    }
    write_json(sdir / "frames_json" / f"{k:06d}.json", record, indent=None)


def visible_masks(scene_dir: Path, im_id: int, n: int) -> list[np.ndarray]:
    """The ``n`` visible masks of frame ``im_id`` written by :func:`write_bop_frame`, from its ``instance/`` map: one
    PNG read instead of ``n`` mask_visib PNGs (the map holds ``g + 1`` exactly where mask_visib ``g`` is set)."""
    inst = read_image(Path(scene_dir) / "instance" / bop.frame_name(im_id), unchanged=True)
    return [inst == g + 1 for g in range(n)]


def merge_scene_files(scene_dir: Path, objects: Sequence[PosedObject], class_names: Sequence[str]) -> None:
    """Merge the per-frame records into scene_camera/scene_gt/scene_gt_info.json, cameras.json, objects.json."""
    scene_dir = Path(scene_dir)
    records = {int(p.stem): read_json(p) for p in sorted((scene_dir / "frames_json").glob("*.json"))}
    write_json(scene_dir / "scene_camera.json", {str(k): r["camera"] for k, r in records.items()})
    write_json(scene_dir / "scene_gt.json", {str(k): r["gt"] for k, r in records.items()})
    write_json(scene_dir / "scene_gt_info.json", {str(k): r["gt_info"] for k, r in records.items()})
    cams = {}
    for k, r in records.items():
        c = r["camera"]
        cams[bop.frame_name(k)] = {
            "K": c["cam_K"], "width": c["width"], "height": c["height"], "R_cam_from_world": c["cam_R_w2c"],
            "t_cam_from_world_m": [t / bop.M_TO_MM for t in c["cam_t_w2c"]],
        }
    write_json(scene_dir / "cameras.json", {"frames": cams})
    write_cameras_tum({"frames": cams}, scene_dir / TUM_NAME)  # the same poses for evo & co, metres
    objs = [
        {"index": i, "name": o.name, "obj_id": o.obj_id, "class_id": o.class_id,
         "class_name": class_names[o.class_id], "R_world_from_obj": o.T_world_from_obj.R.ravel().tolist(),
         "t_world_from_obj_m": o.T_world_from_obj.t.tolist()}
        for i, o in enumerate(objects)
    ]
    write_json(scene_dir / "objects.json", {
        "classes": list(class_names), "objects": objs,
        "gt_index_to_object": {str(k): r["object_index"] for k, r in records.items()},
    })


def save_npz(path: Path, **arrays: np.ndarray) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)

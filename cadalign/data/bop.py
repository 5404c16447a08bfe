"""BOP-format scene writing and reading (https://github.com/thodan/bop_toolkit, docs/bop_datasets_format.md).

BOP stores translations and depth in millimetres: ``depth_mm = png * depth_scale``
and ``cam_t_*`` in mm. cadalign works in metres; the conversion happens only here.

Scene folder layout::

    SCENE/rgb/000000.png              RGB frames
    SCENE/depth/000000.png            uint16, depth_mm / depth_scale (0 = invalid)
    SCENE/mask/000000_000001.png      full silhouette of GT instance 1 of frame 0 (ignoring occluders)
    SCENE/mask_visib/000000_000001.png  its visible part
    SCENE/scene_camera.json  scene_gt.json  scene_gt_info.json
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cadalign.errors import InputError
from cadalign.io import read_image, read_json, write_image
from cadalign.types import Camera, Rigid3

M_TO_MM = 1000.0


@dataclass(frozen=True)
class BopInstance:
    """One annotated object instance in one frame (metres inside cadalign)."""

    obj_id: int
    T_cam_from_obj: Rigid3


def camera_entry(camera: Camera, T_cam_from_world: Rigid3 | None, depth_scale: float) -> dict:
    entry = {
        "cam_K": camera.K.ravel().tolist(),
        "depth_scale": depth_scale,
        "width": camera.width,
        "height": camera.height,
    }
    if T_cam_from_world is not None:
        entry["cam_R_w2c"] = T_cam_from_world.R.ravel().tolist()
        entry["cam_t_w2c"] = (T_cam_from_world.t * M_TO_MM).tolist()
    return entry


def gt_entry(inst: BopInstance) -> dict:
    return {
        "cam_R_m2c": inst.T_cam_from_obj.R.ravel().tolist(),
        "cam_t_m2c": (inst.T_cam_from_obj.t * M_TO_MM).tolist(),
        "obj_id": int(inst.obj_id),
    }


def mask_bbox(mask: np.ndarray) -> list[int]:
    """[x, y, w, h] of a boolean mask; [-1, -1, 0, 0] when empty (BOP's convention)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if len(cols) == 0:
        return [-1, -1, 0, 0]
    return [int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)]


def gt_info_entry(full: np.ndarray, visib: np.ndarray, depth_valid: np.ndarray) -> dict:
    n_all = int(full.sum())
    n_vis = int(visib.sum())
    return {
        "bbox_obj": mask_bbox(full),
        "bbox_visib": mask_bbox(visib),
        "px_count_all": n_all,
        "px_count_valid": int((full & depth_valid).sum()),
        "px_count_visib": n_vis,
        "visib_fract": float(n_vis / n_all) if n_all > 0 else 0.0,
    }


def encode_depth(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metres -> BOP uint16 PNG values; invalid (<= 0, non-finite, or beyond range) -> 0."""
    d = np.asarray(depth_m, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    vals = np.where(valid, np.round(d * M_TO_MM / depth_scale), 0)
    vals = np.where(vals > 65535, 0, vals)
    return vals.astype(np.uint16)


def decode_depth(png: np.ndarray, depth_scale: float) -> np.ndarray:
    """BOP uint16 PNG values -> metres (float32, 0 = invalid)."""
    return (png.astype(np.float64) * depth_scale / M_TO_MM).astype(np.float32)


def frame_name(im_id: int) -> str:
    return f"{im_id:06d}.png"


def mask_name(im_id: int, gt_idx: int) -> str:
    return f"{im_id:06d}_{gt_idx:06d}.png"


def write_frame_gt(
    scene_dir: Path,
    im_id: int,
    depth_m: np.ndarray,
    depth_scale: float,
    masks_full: list[np.ndarray],
    masks_visib: list[np.ndarray],
    *,
    atomic: bool = True,
) -> None:
    """Write one frame's depth PNG and per-instance masks (file by file; see ``write_image`` on ``atomic``)."""
    write_image(scene_dir / "depth" / frame_name(im_id), encode_depth(depth_m, depth_scale), atomic=atomic)
    for g, (full, vis) in enumerate(zip(masks_full, masks_visib, strict=True)):
        write_image(scene_dir / "mask" / mask_name(im_id, g), full.astype(np.uint8) * 255, atomic=atomic)
        write_image(scene_dir / "mask_visib" / mask_name(im_id, g), vis.astype(np.uint8) * 255, atomic=atomic)


@dataclass(frozen=True)
class BopFrame:
    im_id: int
    camera: Camera
    depth_scale: float
    T_cam_from_world: Rigid3 | None
    instances: tuple[BopInstance, ...]
    info: tuple[dict, ...]


class BopScene:
    """Read access to one BOP scene folder (metres on the way out)."""

    def __init__(self, scene_dir: Path) -> None:
        self.dir = Path(scene_dir)
        for name in ("scene_camera.json", "scene_gt.json"):
            if not (self.dir / name).is_file():
                raise InputError(
                    f"{self.dir} is not a BOP scene: {name} is missing (re-run the stage that wrote it)"
                )
        self._cam = read_json(self.dir / "scene_camera.json")
        self._gt = read_json(self.dir / "scene_gt.json")
        info_path = self.dir / "scene_gt_info.json"
        self._info = read_json(info_path) if info_path.is_file() else {}
        missing = sorted(set(self._cam) ^ set(self._gt), key=int)
        if missing:
            raise InputError(
                f"{self.dir}: image ids {missing[:10]} are in only one of scene_camera.json/scene_gt.json"
            )

    @property
    def ids(self) -> list[int]:
        return sorted(int(k) for k in self._cam)

    def frame(self, im_id: int) -> BopFrame:
        key = str(im_id)
        if key not in self._cam:
            raise InputError(f"{self.dir}: no image id {im_id} in scene_camera.json")
        c = self._cam[key]
        K = np.array(c["cam_K"], dtype=np.float64).reshape(3, 3)
        w, h = c.get("width"), c.get("height")
        if w is None or h is None:
            h, w = read_image(self.dir / "rgb" / frame_name(im_id)).shape[:2]
        T = None
        if "cam_R_w2c" in c:
            T = Rigid3(np.reshape(c["cam_R_w2c"], (3, 3)), np.asarray(c["cam_t_w2c"]) / M_TO_MM)
        insts = tuple(
            BopInstance(
                int(g["obj_id"]),
                Rigid3(np.reshape(g["cam_R_m2c"], (3, 3)), np.asarray(g["cam_t_m2c"]) / M_TO_MM),
            )
            for g in self._gt[key]
        )
        return BopFrame(
            im_id, Camera(K, w, h), float(c.get("depth_scale", 1.0)), T, insts, tuple(self._info.get(key, []))
        )

    def rgb(self, im_id: int) -> np.ndarray:
        return read_image(self.dir / "rgb" / frame_name(im_id))

    def depth_m(self, im_id: int) -> np.ndarray:
        png = read_image(self.dir / "depth" / frame_name(im_id), unchanged=True)
        return decode_depth(png, self.frame(im_id).depth_scale)

    def mask(self, im_id: int, gt_idx: int, *, visible: bool = True) -> np.ndarray:
        folder = "mask_visib" if visible else "mask"
        return read_image(self.dir / folder / mask_name(im_id, gt_idx), unchanged=True) > 127

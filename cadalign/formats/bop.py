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

import math
import numbers
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


MAX_DEPTH_SCALE = 1e30
"""Largest accepted ``depth_scale``: 65535 units of it must still fit a float32 depth in metres."""


def _check_depth_scale(depth_scale: float) -> float:
    if not (_is_number(depth_scale) and 0 < depth_scale <= MAX_DEPTH_SCALE):
        raise InputError(f"depth_scale must be a number in (0, {MAX_DEPTH_SCALE:g}] (mm per PNG unit), "
                         f"got {depth_scale!r:.40}")
    return float(depth_scale)


def encode_depth(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metres -> BOP uint16 PNG values; invalid (<= 0, non-finite, or beyond range) -> 0, without warnings."""
    scale = _check_depth_scale(depth_scale)
    d = np.asarray(depth_m, dtype=np.float64)
    valid = np.isfinite(d) & (d > 0)
    with np.errstate(over="ignore", invalid="ignore"):  # beyond 65535 units is "no depth", like NaN
        vals = np.where(valid, np.round(np.where(valid, d, 0.0) * M_TO_MM / scale), 0)
    vals = np.where(vals > 65535, 0, vals)
    return vals.astype(np.uint16)


def decode_depth(png: np.ndarray, depth_scale: float) -> np.ndarray:
    """BOP uint16 PNG values -> metres (float32, 0 = invalid)."""
    return (png.astype(np.float64) * _check_depth_scale(depth_scale) / M_TO_MM).astype(np.float32)


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


def _is_number(v: object) -> bool:
    """A finite JSON number (not a bool; integers beyond float range are not)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        return False
    try:
        return math.isfinite(float(v))
    except OverflowError:
        return False


_JSON_NUMBER = (int, float)  # exact types: bool (a subclass of int) is not a number here
_Rows = list[tuple[str, str, list]]  # (where, key, values) of the numeric entries to check in one batch


def _numbers(entry: dict, key: str, n: int, where: str, rows: _Rows) -> None:
    """Check that ``entry[key]`` is a list of ``n`` JSON numbers; queue it in ``rows`` for the numeric checks."""
    v = entry.get(key)
    if not isinstance(v, list) or len(v) != n or not all(type(x) in _JSON_NUMBER for x in v):
        raise InputError(f"{where}: '{key}' must be a list of {n} finite numbers, got {v!r:.80}; "
                         "re-export the scene or fix the entry")
    rows.append((where, key, v))


def _first_bad(rows: _Rows, n: int, rotation: bool) -> tuple[int, str] | None:
    """Index and problem of the first row that is non-finite (or not a rotation), vectorised over all rows."""
    try:
        arr = np.array([r[2] for r in rows], dtype=np.float64).reshape(-1, n)
    except OverflowError:  # an integer beyond float range
        bad = [i for i, r in enumerate(rows) if not all(_is_number(x) for x in r[2])]
        return bad[0], "finite"
    nonfinite = np.flatnonzero(~np.all(np.isfinite(arr), axis=1))
    if len(nonfinite):
        return int(nonfinite[0]), "finite"
    if rotation:
        R = arr.reshape(-1, 3, 3)
        with np.errstate(over="ignore", invalid="ignore"):
            err = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
            bad = (np.abs(R).max(axis=(1, 2)) > 2) | ~(err <= 1e-3) | ~(np.linalg.det(R) > 0)
        if bad.any():
            return int(np.flatnonzero(bad)[0]), "rotation"
    return None


def _check_rows(rows: _Rows, n: int, *, rotation: bool = False) -> None:
    found = _first_bad(rows, n, rotation) if rows else None
    if found is None:
        return
    where, key, v = rows[found[0]]
    if found[1] == "finite":
        raise InputError(f"{where}: '{key}' must be a list of {n} finite numbers, got {v!r:.80}; "
                         "re-export the scene or fix the entry")
    raise InputError(f"{where}: '{key}' is not a rotation matrix (row-major 3x3, R R^T = I, det +1); "
                     "re-export the scene or fix the entry")


def _table(data: object, path: Path, kind: type) -> dict[str, object]:
    """Check a BOP json's top level: an object whose keys are image ids and whose values are ``kind``."""
    if not isinstance(data, dict):
        raise InputError(f"{path}: the top level must be an object keyed by image id, got {type(data).__name__}")
    for k, v in data.items():
        if not (k.isascii() and k.isdigit()):
            raise InputError(f"{path}: key {k!r:.40} is not an image id (a non-negative integer)")
        if not isinstance(v, kind):
            raise InputError(f"{path}: the entry of image {k} must be a JSON {'object' if kind is dict else 'list'}")
    return data


def _check_camera(c: dict, where: str, Ks: _Rows, Rs: _Rows, ts: _Rows) -> None:
    _numbers(c, "cam_K", 9, where, Ks)
    if "depth_scale" in c and not (_is_number(c["depth_scale"]) and 0 < c["depth_scale"] <= MAX_DEPTH_SCALE):
        raise InputError(f"{where}: 'depth_scale' must be a positive number (<= {MAX_DEPTH_SCALE:g}), got "
                         f"{c['depth_scale']!r:.40}")
    for key in ("width", "height"):
        if key in c and not (type(c[key]) is int and c[key] > 0):
            raise InputError(f"{where}: '{key}' must be a positive integer, got {c[key]!r:.40}")
    if ("width" in c) != ("height" in c):
        raise InputError(f"{where}: give both 'width' and 'height' or neither")
    if ("cam_R_w2c" in c) != ("cam_t_w2c" in c):
        raise InputError(f"{where}: give both 'cam_R_w2c' and 'cam_t_w2c' or neither")
    if "cam_R_w2c" in c:
        _numbers(c, "cam_R_w2c", 9, where, Rs)
        _numbers(c, "cam_t_w2c", 3, where, ts)


def _check_instances(gts: list, where: str, Rs: _Rows, ts: _Rows) -> None:
    for i, g in enumerate(gts):
        w = f"{where}, instance {i}"
        if not isinstance(g, dict):
            raise InputError(f"{w}: must be a JSON object with cam_R_m2c, cam_t_m2c and obj_id")
        _numbers(g, "cam_R_m2c", 9, w, Rs)
        _numbers(g, "cam_t_m2c", 3, w, ts)
        oid = g.get("obj_id")
        if not (type(oid) is int and oid >= 1):
            raise InputError(f"{w}: 'obj_id' must be a positive integer (BOP model ids start at 1), got {oid!r:.40}")


def _check_focal(Ks: _Rows) -> None:
    for where, key, K in Ks:
        if not (K[0] > 0 and K[4] > 0):
            raise InputError(f"{where}: '{key}' must have positive focal lengths, got {K}")


class BopScene:
    """Read access to one BOP scene folder (metres on the way out).

    The json files are validated when the scene is opened: a missing key, a wrong type, a non-finite
    number, a non-rotation ``R`` or image ids that disagree between the files raise
    :class:`~cadalign.errors.InputError` naming the file, the image id and the key.
    """

    def __init__(self, scene_dir: Path) -> None:
        self.dir = Path(scene_dir)
        self._frames: dict[int, BopFrame] = {}  # parsed once: every image read checks its size against its frame
        for name in ("scene_camera.json", "scene_gt.json"):
            if not (self.dir / name).is_file():
                raise InputError(
                    f"{self.dir} is not a BOP scene: {name} is missing (re-run the stage that wrote it)"
                )
        cam_path, gt_path, info_path = (self.dir / n for n in ("scene_camera.json", "scene_gt.json",
                                                                "scene_gt_info.json"))
        self._cam = _table(read_json(cam_path), cam_path, dict)
        self._gt = _table(read_json(gt_path), gt_path, list)
        self._info = _table(read_json(info_path), info_path, list) if info_path.is_file() else {}
        missing = sorted(set(self._cam) ^ set(self._gt), key=int)
        if missing:
            raise InputError(
                f"{self.dir}: image ids {missing[:10]} are in only one of scene_camera.json/scene_gt.json; "
                "re-run the stage that wrote the scene (or delete the stray entries)"
            )
        self._check_numbers(cam_path, gt_path)
        for k, infos in self._info.items():
            if k not in self._gt or len(infos) != len(self._gt[k]):
                n_gt = len(self._gt[k]) if k in self._gt else "no"
                raise InputError(f"{info_path}, image {k}: {len(infos)} entries but scene_gt.json has {n_gt} "
                                 "instances for it; re-run the stage that wrote the scene")
            if not all(isinstance(i, dict) for i in infos):
                raise InputError(f"{info_path}, image {k}: every entry must be a JSON object")

    def _check_numbers(self, cam_path: Path, gt_path: Path) -> None:
        """Structure entry by entry, then every K, R and t at once (vectorised: large scenes open fast)."""
        Ks: _Rows = []
        Rs: _Rows = []
        ts: _Rows = []
        for k, c in self._cam.items():
            _check_camera(c, f"{cam_path}, image {k}", Ks, Rs, ts)
        for k, gts in self._gt.items():
            _check_instances(gts, f"{gt_path}, image {k}", Rs, ts)
        _check_rows(Ks, 9)
        _check_focal(Ks)
        _check_rows(Rs, 9, rotation=True)
        _check_rows(ts, 3)

    @property
    def ids(self) -> list[int]:
        return sorted(int(k) for k in self._cam)

    def _read(self, folder: str, name: str, im_id: int, *, unchanged: bool) -> np.ndarray:
        path = self.dir / folder / name
        if not path.is_file():
            raise InputError(f"{path} is missing: image {im_id} is listed in scene_camera.json but has no {folder} "
                             "file; re-run the stage that wrote the scene")
        return read_image(path, unchanged=unchanged)

    def _check_size(self, img: np.ndarray, im_id: int, folder: str, name: str) -> np.ndarray:
        cam = self.frame(im_id).camera
        if img.shape[:2] != (cam.height, cam.width):
            raise InputError(f"{self.dir / folder / name} is {img.shape[1]}x{img.shape[0]} but scene_camera.json "
                             f"says image {im_id} is {cam.width}x{cam.height}; re-run the stage that wrote the scene")
        return img

    def frame(self, im_id: int) -> BopFrame:
        """Image ``im_id``'s camera, pose and instances (parsed on the first call, then remembered)."""
        im_id = int(im_id)
        if im_id not in self._frames:
            self._frames[im_id] = self._parse_frame(im_id)
        return self._frames[im_id]

    def _parse_frame(self, im_id: int) -> BopFrame:
        key = str(im_id)
        if key not in self._cam:
            raise InputError(f"{self.dir}: no image id {im_id} in scene_camera.json")
        c = self._cam[key]
        K = np.array(c["cam_K"], dtype=np.float64).reshape(3, 3)
        w, h = c.get("width"), c.get("height")
        if w is None or h is None:
            h, w = self._read("rgb", frame_name(im_id), im_id, unchanged=False).shape[:2]
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
        name = frame_name(im_id)
        return self._check_size(self._read("rgb", name, im_id, unchanged=False), im_id, "rgb", name)

    def depth_m(self, im_id: int) -> np.ndarray:
        name = frame_name(im_id)
        png = self._read("depth", name, im_id, unchanged=True)
        if png.ndim != 2 or png.dtype != np.uint16:
            raise InputError(f"{self.dir / 'depth' / name} must be a single-channel 16-bit PNG (BOP depth), got "
                             f"{png.dtype} with shape {png.shape}; re-write it with the depth in mm / depth_scale")
        return decode_depth(self._check_size(png, im_id, "depth", name), self.frame(im_id).depth_scale)

    def mask(self, im_id: int, gt_idx: int, *, visible: bool = True) -> np.ndarray:
        folder = "mask_visib" if visible else "mask"
        name = mask_name(im_id, gt_idx)
        img = self._read(folder, name, im_id, unchanged=True)
        if img.ndim != 2:
            img = img[..., 0]
        return self._check_size(img, im_id, folder, name) > 127

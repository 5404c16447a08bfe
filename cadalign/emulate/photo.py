"""GenLaM from any photograph: photo -> depth, camera, classes, panes -> layered mesh -> LiDAR scan + pictures.

Depth comes from the user's pretrained checkpoint (:mod:`cadalign.emulate.pretrained`: metric depth, or
relative disparity made depth by ``1 / disparity`` and scaled by ``--scale-from``; with a reference depth
map, scale and shift of the disparity are fitted) or from an ``.npz`` point map (``rgb`` + ``points``
(H, W, 3) in camera axes, e.g. MoGe's output, or ``depth_m`` + per-pixel ``rays``: its ``z + dz`` of eq. (1)
is the depth). The camera: :mod:`cadalign.emulate.photo_camera`. Classes: a SegFormer checkpoint or a
``cadalign train seg`` run. Optionally the photo is super-resolved (:mod:`cadalign.emulate.superres`) before
depth and the depth averaged back to the photo's grid. Panes: the classes named like glass/windows, or a user
mask. Relative depth without ``--scale-from`` is scaled to a median depth of 1 and the summary says
``"metric": false``: the mesh then has no metric scale (nor is the disparity's shift known).

:func:`run` writes into ``out_dir``: ``photo_input.npz`` (rgb, depth_m, K, class_id, pane_mask,
class_names: an image source of :mod:`cadalign.emulate.sources`), ``layered_mesh.ply``, ``preview_rgb.png`` /
``preview_class.png`` (the mesh from its own camera), ``scan.npz`` / ``scan.ply`` (a LiDAR at the camera,
colour, class and pane per point), ``lidar_pose.json`` (that pose, for ``emulate lidar --pose``),
``contact.png`` (photo, depth, classes, a novel view of the mesh, the scan), ``photo.json`` (camera source,
eq. (1) residual, scale, seconds per stage) and, last, ``emulate.json``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cadalign.emulate import figures, lidar, views
from cadalign.emulate.layered_mesh import ImageInput, LayeredMeshConfig, mesh_from_image
from cadalign.emulate.photo_camera import (
    ScaleFrom,
    fit_disparity,
    parse_scale,
    photo_camera,
    reference_depth,
    scale_factor,
)
from cadalign.emulate.pretrained import DepthOutput, PretrainedConfig, SegModel, load_depth_model, load_seg_model
from cadalign.emulate.run import SENSOR_FROM_CAM, SUMMARY
from cadalign.emulate.sources import write_ply
from cadalign.errors import InputError
from cadalign.fuse.predictors import seg_predictor
from cadalign.io import atomic_path, prepare_stage_dir, read_image, write_image, write_json
from cadalign.types import Camera, Rigid3

log = logging.getLogger(__name__)
PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp")


def _scan_default() -> lidar.LidarConfig:
    return lidar.LidarConfig(channels=64, vfov_deg=(-40.0, 40.0), horizontal_res_deg=0.25, min_range_m=0.01,
                             max_range_m=1000.0, range_noise_m=0.0)


@dataclass(frozen=True)
class PhotoConfig:
    mesh: LayeredMeshConfig = field(default_factory=LayeredMeshConfig)
    """Layered mesh from the predicted depth (cuts at jumps, panes)."""
    pretrained: PretrainedConfig = field(default_factory=PretrainedConfig)
    """Network input size and device."""
    default_hfov_deg: float = 70.0
    """Field of view assumed when nothing gives one, degrees (a typical ROV camera behind a dome port)."""
    scan: lidar.LidarConfig = field(default_factory=_scan_default)
    """The LiDAR at the camera for scan.npz and the contact picture (noise-free, +-40 deg: the photo's view)."""


@dataclass(frozen=True)
class PhotoResult:
    """A photo lifted to an image source, and how.

    Attributes:
        image: rgb, metric (or unit-median) depth, K, classes, pane mask, class names.
        info: camera source, hfov, eq. (1) residual, depth kind, scale, whether metric, seconds per stage.
    """

    image: ImageInput
    info: dict[str, Any]


def read_photo(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """``(rgb (H, W, 3) uint8, point map (H, W, 3) or None)`` of a photo file or an ``.npz``: ``rgb`` with
    ``points`` (H, W, 3), or with ``depth_m`` (H, W) along ``rays`` (H, W, 3; camera-frame directions of the
    pixels, any length: the point is the ray scaled to z = depth)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"photo not found: {path}")
    if path.suffix.lower() == ".npz":
        with np.load(path) as z:
            has = set(z.files)
            if "rgb" not in has or not ("points" in has or {"depth_m", "rays"} <= has):
                raise InputError(f"{path}: a point-map .npz needs 'rgb' (H, W, 3) and 'points' (H, W, 3), or "
                                 "'depth_m' (H, W) and 'rays' (H, W, 3)")
            rgb = np.asarray(z["rgb"])
            pts = np.asarray(z["points"], np.float64) if "points" in has else _points_from_rays(
                np.asarray(z["depth_m"], np.float64), np.asarray(z["rays"], np.float64))
        if pts.shape != rgb.shape[:2] + (3,):
            raise InputError(f"{path}: points {pts.shape} must be (H, W, 3) matching rgb {rgb.shape}")
        return rgb[..., :3].astype(np.uint8), pts
    if path.suffix.lower() not in PHOTO_SUFFIXES:
        raise InputError(f"{path}: a photo must be one of {', '.join(PHOTO_SUFFIXES)} or a point-map .npz")
    return read_image(path), None


def _points_from_rays(depth_m: np.ndarray, rays: np.ndarray) -> np.ndarray:
    if rays.shape != depth_m.shape + (3,):
        raise InputError(f"rays {rays.shape} must be (H, W, 3) matching depth_m {depth_m.shape}")
    ok = np.isfinite(depth_m) & (np.nan_to_num(depth_m) > 0) & (np.nan_to_num(rays[..., 2]) > 0)
    z = np.where(ok, rays[..., 2], 1.0)
    return np.where(ok[..., None], rays / z[..., None] * np.where(ok, depth_m, 0.0)[..., None], np.nan)


def depth_from_output(out: DepthOutput) -> np.ndarray:
    """Z-depth (metric, or up to scale for disparity: ``1 / disparity``; <= 0 disparity = no depth)."""
    v = np.asarray(out.value, np.float64)
    if out.kind == "metric":
        return np.where(np.isfinite(v) & (np.nan_to_num(v) > 0), v, 0.0)
    good = np.isfinite(v) & (np.nan_to_num(v) > 1e-6 * max(float(np.nanmax(np.abs(v), initial=0.0)), 1e-30))
    return np.where(good, 1.0 / np.where(good, v, 1.0), 0.0)


def lift_photo(photo: Path, cfg: PhotoConfig, *, depth_fn: Callable[[np.ndarray], DepthOutput] | None = None,
               seg: SegModel | None = None, seg_fn: Callable[[np.ndarray], np.ndarray] | None = None,
               hfov_deg: float | None = None, calib: Path | None = None, scale_from: ScaleFrom | None = None,
               pane_mask: np.ndarray | None = None,
               upscale: Callable[[np.ndarray], np.ndarray] | None = None) -> PhotoResult:
    """Depth, camera, classes and panes of one photo (see the module docstring); seconds per stage in ``info``.

    Raises:
        InputError: neither a depth model nor a point map, or any input error of the steps.
    """
    rgb, points = read_photo(photo)
    H, W = rgb.shape[:2]
    info: dict[str, Any] = {}
    t0 = time.perf_counter()
    cam = photo_camera(W, H, calib=calib, hfov_deg=hfov_deg, photo=Path(photo), points=points,
                       default_hfov_deg=cfg.default_hfov_deg)
    if depth_fn is not None:
        out = depth_fn(rgb) if upscale is None else _on_upscaled(depth_fn, upscale, rgb, info)
        depth, info["depth_kind"] = depth_from_output(out), out.kind
    elif points is not None:
        depth, info["depth_kind"] = points[..., 2] + cam.shift, "point_map"
        depth = np.where(np.isfinite(depth) & (np.nan_to_num(depth) > 0), depth, 0.0)
    else:
        raise InputError(f"{photo}: a photo has no depth; pass --depth-model DIR (a local transformers "
                         "checkpoint) or give an .npz point map")
    info["depth_s"] = time.perf_counter() - t0
    disparity = out.value if depth_fn is not None and out.kind == "disparity" else None
    depth, info["scale"], info["metric"] = _scaled(depth, disparity, scale_from, cam.K)
    t1 = time.perf_counter()
    cls, names = None, ()
    if seg is not None or seg_fn is not None:
        prob = (seg.predict if seg is not None else seg_fn)(rgb)  # type: ignore[misc]
        if np.shape(prob)[1:] != (H, W):
            raise InputError(f"the segmentation model returned {np.shape(prob)}; expected (C, {H}, {W})")
        cls = np.asarray(prob).argmax(0).astype(np.int32)
        names = seg.class_names if seg is not None else ()
    if pane_mask is None and seg is not None and cls is not None and seg.pane_classes():
        pane_mask = np.isin(cls, seg.pane_classes())
    info["classes_s"] = time.perf_counter() - t1
    info |= {"camera": cam.source, "hfov_deg": cam.hfov_deg, "K": cam.K.tolist(),
             "eq1_residual_px": cam.residual_px, "pane_pixels": 0 if pane_mask is None else int(pane_mask.sum())}
    return PhotoResult(ImageInput(rgb, depth, cam.K, class_id=cls, pane_mask=pane_mask, class_names=names), info)


def _on_upscaled(depth_fn: Callable[[np.ndarray], DepthOutput], upscale: Callable[[np.ndarray], np.ndarray],
                 rgb: np.ndarray, info: dict) -> DepthOutput:
    """Depth of the super-resolved photo, area-averaged back to the photo's grid (the mesh keeps its size)."""

    t = time.perf_counter()
    big = upscale(rgb)
    info["sr_s"], info["sr_scale"] = time.perf_counter() - t, big.shape[1] / rgb.shape[1]
    out = depth_fn(big)
    H, W = rgb.shape[:2]
    return DepthOutput(cv2.resize(np.asarray(out.value, np.float64), (W, H), interpolation=cv2.INTER_AREA), out.kind)


def _scaled(depth: np.ndarray, disparity: np.ndarray | None, spec: ScaleFrom | None,
            K: np.ndarray) -> tuple[np.ndarray, float | list[float], bool]:
    """Metric depth, the scale (or disparity ``[a, b]``) applied, and whether the result is metric."""
    if spec is not None and disparity is not None and spec.kind in ("depth", "cad"):
        a, b = fit_disparity(disparity, reference_depth(spec, depth.shape, K))
        inv = a * disparity + b
        good = np.isfinite(inv) & (np.nan_to_num(inv) > 0)
        return np.where(good, 1.0 / np.where(good, inv, 1.0), 0.0), [a, b], True
    if spec is not None:
        s = scale_factor(depth, spec, K)
        return depth * s, s, True
    if disparity is not None:
        ok = depth > 0
        s = 1.0 / float(np.median(depth[ok])) if ok.any() else 1.0
        log.warning("relative depth and no --scale-from: the mesh has NO metric scale (median depth set to 1); "
                    "pass --scale-from distance:METRES, pixel:U,V:METRES or depth:PATH")
        return depth * s, s, False
    return depth, 1.0, True


def camera_lidar_pose() -> Rigid3:
    """The LiDAR pose (x forward, y left, z up) at the photo's camera, in the camera frame of the mesh."""
    return Rigid3(SENSOR_FROM_CAM.T, np.zeros(3))


def novel_pose(depth_m: np.ndarray, angle_deg: float = 25.0) -> Rigid3:
    """The camera turned ``angle_deg`` about its y axis around the median scene point (shows the relief)."""
    ok = depth_m > 0
    pivot = np.array([0.0, 0.0, float(np.median(depth_m[ok])) if ok.any() else 1.0])
    a = np.radians(angle_deg)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    return Rigid3(R, pivot - R @ pivot)


def run(cfg: PhotoConfig, photo: Path, out_dir: Path, *, depth_model: Path | None = None,
        seg_model: Path | None = None, seg_run: Path | None = None, sr_model: Path | None = None,
        hfov_deg: float | None = None,
        calib: Path | None = None, scale_from: str | None = None, pane_mask: Path | None = None,
        overwrite: bool = False) -> Path:
    """Photo -> layered mesh, scan and pictures in ``out_dir`` (see the module docstring); returns ``out_dir``."""
    photo, out_dir = Path(photo), Path(out_dir)
    rgb_check, _ = read_photo(photo)
    spec = parse_scale(scale_from) if scale_from else None
    mask = _read_mask(pane_mask, rgb_check.shape[:2]) if pane_mask is not None else None
    stat = photo.stat()
    record = {"config": cfg, "photo": str(photo.resolve()), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns,
              "models": {k: str(v) for k, v in (("depth", depth_model), ("seg", seg_model), ("seg_run", seg_run),
                                                        ("sr", sr_model))
                         if v is not None},
              "hfov_deg": hfov_deg, "calib": None if calib is None else str(calib), "scale_from": scale_from,
              "pane_mask": None if pane_mask is None else str(pane_mask)}
    if prepare_stage_dir(out_dir, "emulate_photo", record, overwrite=overwrite) and (out_dir / SUMMARY).is_file():
        log.info("%s: finished photo emulation found, reusing it", out_dir)
        return out_dir
    (out_dir / SUMMARY).unlink(missing_ok=True)  # this run's mark of completion, not an older run's (--overwrite)
    t = time.perf_counter()
    depth_fn = load_depth_model(depth_model, cfg.pretrained) if depth_model is not None else None
    seg = load_seg_model(seg_model, cfg.pretrained) if seg_model is not None else None
    seg_fn = _trained_seg(seg_run, cfg.pretrained.device) if seg_run is not None else None
    upscale = None
    if sr_model is not None:
        # lazy: pulls torch
        from cadalign.emulate.superres import load_sr_model  # torch at import: only with --sr-model

        upscale = load_sr_model(sr_model, cfg.pretrained.device)
    load_s = time.perf_counter() - t
    res = lift_photo(photo, cfg, depth_fn=depth_fn, seg=seg, seg_fn=seg_fn, hfov_deg=hfov_deg, calib=calib,
                     scale_from=spec, pane_mask=mask, upscale=upscale)
    info = res.info | {"load_models_s": load_s}
    info |= _write_outputs(cfg, res.image, out_dir, photo.stem, info)
    write_json(out_dir / "photo.json", info)
    write_json(out_dir / SUMMARY, {"sensor": "mesh", "faces": info["faces"], "photo": str(photo)})
    log.info("photo %s: depth %.2f s, classes %.2f s, mesh %.2f s, scan %.2f s", photo.name, info["depth_s"],
             info["classes_s"], info["mesh_s"], info["scan_s"])
    return out_dir


def _write_outputs(cfg: PhotoConfig, inp: ImageInput, out: Path, title: str, info: dict) -> dict:
    with atomic_path(out / "photo_input.npz") as tmp, open(tmp, "wb") as fh:
        extra = {k: v for k, v in (("class_id", inp.class_id), ("pane_mask", inp.pane_mask)) if v is not None}
        np.savez_compressed(fh, rgb=inp.rgb, depth_m=inp.depth_m, K=inp.K,
                            class_names=np.asarray(inp.class_names, dtype=str), **extra)
    t = time.perf_counter()
    mesh = mesh_from_image(inp, cfg.mesh)
    mesh_s = time.perf_counter() - t
    write_ply(mesh, out / "layered_mesh.ply")
    t = time.perf_counter()
    scan = lidar.scan(mesh, camera_lidar_pose(), cfg.scan)
    scan_s = time.perf_counter() - t
    lidar.write_npz(scan, out / "scan.npz")
    lidar.write_ply(scan, out / "scan.ply")
    write_json(out / "lidar_pose.json", {"T_world_from_sensor": camera_lidar_pose().matrix().tolist(),
                                         "frame": "the photo's camera (x right, y down, z forward)"})
    H, W = np.shape(inp.depth_m)
    cam = Camera(inp.K, W, H)
    own = views.render(mesh, cam, Rigid3())
    write_image(out / "preview_rgb.png", own.rgb)
    write_image(out / "preview_class.png", figures.class_colours(own.class_id))
    novel = views.render(mesh, cam, novel_pose(np.asarray(inp.depth_m)))
    figures.contact_figure(inp.rgb, np.asarray(inp.depth_m), inp.class_id, novel.rgb, scan, out / "contact.png",
                           inp.class_names, f"{title}: camera {info['camera']}, hfov {info['hfov_deg']:.1f} deg, "
                           f"{'metric' if info['metric'] else 'NO metric scale'}")
    return {"faces": mesh.n_faces, "vertices": len(mesh.vertices_m), "panes": int(mesh.pane_id.max(initial=0)),
            "scan_returns": len(scan.range_m), "scan_pane_returns": int((scan.pane_id > 0).sum()),
            "mesh_s": mesh_s, "scan_s": scan_s}


def _read_mask(path: Path, shape: tuple[int, ...]) -> np.ndarray:
    m = read_image(Path(path), unchanged=True)
    m = m if m.ndim == 2 else m[..., 0]
    if m.shape != tuple(shape):
        raise InputError(f"--pane-mask {path} is {m.shape[1]}x{m.shape[0]}; the photo is {shape[1]}x{shape[0]}")
    return m > 0


def _trained_seg(run_dir: Path, device: str) -> Callable[[np.ndarray], np.ndarray]:
    return seg_predictor(run_dir, None, device, None)


"""The emulation stage on disk: SOURCE + sensor config + pose -> scan / ping / view / layered mesh files.

``run(sensor, cfg, source, out_dir, pose=...)`` writes, atomically, into ``out_dir``:

- lidar: ``scan.npz``, ``scan.ply`` (points with colour, range, class, part, pane, ring), ``lidar_class.png``;
- sonar: ``sonar.npz`` (intensity, clean intensity, class per cell, ranges, bearings), ``sonar_polar.png``
  (8-bit log intensity, range x bearing), ``sonar.png`` (fan + class picture);
- view: ``rgb.png``, ``depth.png`` (uint16, millimetres), ``class.png`` (colours), ``view.npz`` (all layers);
- mesh: ``layered_mesh.ply`` (per-face colour/class/part/pane) and ``preview_rgb.png``/``preview_class.png``
  rendered back from the image's own camera;

plus ``cadalign_stage.json`` (resolved config, source, pose, version) and ``emulate.json`` (summary; written
last, so it marks a finished run). A finished run with the same config is reused; another config in the
same folder is refused unless ``overwrite``.

Poses: LiDAR and sonar frames are x forward, y left, z up; views use the OpenCV camera (x right, y down,
z forward). :func:`default_pose` picks the first trajectory pose of a scene spec (the ROV camera) when no
pose is given.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from cadalign.emulate import figures, layered_mesh, lidar, sonar, views
from cadalign.emulate.mesh import LayeredMesh
from cadalign.emulate.sources import (
    MESH_SUFFIXES,
    SCENE_SUFFIXES,
    DepthFn,
    SegFn,
    load_source,
    read_image_input,
    write_ply,
)
from cadalign.errors import InputError
from cadalign.io import atomic_path, prepare_stage_dir, read_json, write_image, write_json
from cadalign.sim.trajectory import frame_poses
from cadalign.types import Camera, Rigid3

log = logging.getLogger(__name__)
Sensor = Literal["lidar", "sonar", "view", "mesh"]
SUMMARY = "emulate.json"
CONFIGS: dict[str, tuple[type, dict[str, Any], str]] = {
    "lidar": (lidar.LidarConfig, lidar.PRESETS, "hdl32"),
    "sonar": (sonar.SonarConfig, sonar.PRESETS, "default"),
    "view": (views.ViewConfig, views.PRESETS, "default"),
    "mesh": (layered_mesh.LayeredMeshConfig, layered_mesh.PRESETS, "default"),
}
"""sensor -> (config class, presets, default preset)."""

SENSOR_FROM_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Rotation taking OpenCV camera axes (x right, y down, z forward) to sensor axes (x forward, y left, z up)."""


def sensor_pose_from_camera(T_world_from_cam: Rigid3) -> Rigid3:
    """The LiDAR/sonar pose looking where an OpenCV camera looks (same centre, x = camera z)."""
    return Rigid3(T_world_from_cam.R @ SENSOR_FROM_CAM.T, T_world_from_cam.t)


def parse_pose(text: str) -> Rigid3:
    """A world pose from ``x,y,z``, ``x,y,z,roll,pitch,yaw`` (degrees, extrinsic xyz as in scene specs) or a
    JSON file holding a 4x4 ``T_world_from_sensor`` (or ``T_world_from_cam``) matrix."""
    p = Path(text)
    if p.suffix.lower() == ".json":
        data = read_json(p)
        M = data.get("T_world_from_sensor", data.get("T_world_from_cam")) if isinstance(data, dict) else data
        try:
            return Rigid3.from_matrix(np.asarray(M, dtype=np.float64))
        except (ValueError, TypeError) as exc:
            raise InputError(f"{p}: expected a 4x4 matrix under 'T_world_from_sensor': {exc}") from exc
    try:
        vals = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError:
        vals = []
    if len(vals) not in (3, 6) or not np.all(np.isfinite(vals)):
        raise InputError(f"--pose {text!r}: give 'x,y,z', 'x,y,z,roll,pitch,yaw' (metres, degrees) or a .json file")

    R = Rotation.from_euler("xyz", vals[3:] if len(vals) == 6 else [0, 0, 0], degrees=True).as_matrix()
    return Rigid3(R, vals[:3])


def default_pose(source: Path, sensor: Sensor) -> Rigid3:
    """The pose used without ``--pose``: a scene's first trajectory pose, an image's own camera."""
    source = Path(source)
    if source.suffix.lower() in SCENE_SUFFIXES:
        from cadalign.sim.spec import load_scene  # lazy: pulls cv2; keeps `cadalign --help` light

        spec = load_scene(source)
        T_cam = frame_poses(spec.trajectory, 1, spec.seed)[0]
    elif source.suffix.lower() in MESH_SUFFIXES:
        raise InputError(f"{source}: a mesh source has no default pose; pass --pose x,y,z[,roll,pitch,yaw]")
    else:
        T = read_image_input(source).T_world_from_cam
        T_cam = Rigid3() if T is None else Rigid3.from_matrix(T)
    if sensor == "lidar":
        return Rigid3(np.eye(3), T_cam.t)  # a spinning LiDAR is mounted level
    return sensor_pose_from_camera(T_cam) if sensor == "sonar" else T_cam


def run(sensor: Sensor, cfg: Any, source: Path, out_dir: Path, *, pose: Rigid3 | None = None,
        overwrite: bool = False, depth_fn: DepthFn | None = None, seg_fn: SegFn | None = None,
        models: dict[str, str] | None = None, unit: str | None = None) -> Path:
    """Emulate ``sensor`` in ``source`` and write its files to ``out_dir`` (see the module docstring).

    For an image source, ``depth_fn`` / ``seg_fn`` replace the ground-truth depth / classes by network
    predictions; ``models`` names them (e.g. the run folders) in the recorded config. ``unit`` is a mesh file's
    length unit (:func:`cadalign.emulate.sources.load_source`).
    """
    if sensor not in CONFIGS:
        raise InputError(f"unknown sensor {sensor!r}; allowed: {', '.join(CONFIGS)}")
    source, out_dir = Path(source), Path(out_dir)
    if not source.exists():
        raise InputError(f"SOURCE not found: {source}")
    if sensor == "mesh" and (source.suffix.lower() in SCENE_SUFFIXES or source.suffix.lower() in MESH_SUFFIXES):
        raise InputError(f"{source}: 'emulate mesh' builds a layered mesh from one image; give an RGB frame of a "
                         "BOP scene (SCENE/rgb/NNNNNN.png) or an .npz with rgb, depth_m and K")
    T = pose if pose is not None else (None if sensor == "mesh" else default_pose(source, sensor))
    stat = source.stat()
    record = {"sensor": sensor, "config": cfg, "source": str(source.resolve()),
              "source_size": stat.st_size, "source_mtime_ns": stat.st_mtime_ns,
              "T_world_from_sensor": None if T is None else T.matrix().tolist(), "models": models or {}}
    if unit is not None:  # recorded only when given, so the records of earlier runs stay valid
        record["unit"] = unit
    done = prepare_stage_dir(out_dir, f"emulate_{sensor}", record, overwrite=overwrite)
    if done and (out_dir / SUMMARY).is_file():
        log.info("%s: finished %s emulation found, reusing it", out_dir, sensor)
        return out_dir
    t0 = time.perf_counter()
    mesh = load_source(source, image_config=cfg if sensor == "mesh" else None, depth_fn=depth_fn, seg_fn=seg_fn,
                       unit=unit)
    t1 = time.perf_counter()
    summary = {"sensor": sensor, "faces": mesh.n_faces, "load_s": t1 - t0}
    summary |= _WRITERS[sensor](mesh, cfg, T, out_dir, source)
    summary["emulate_s"] = time.perf_counter() - t1
    write_json(out_dir / SUMMARY, summary)
    return out_dir


def _write_lidar(mesh: LayeredMesh, cfg: lidar.LidarConfig, T: Rigid3, out: Path, source: Path) -> dict:
    s = lidar.scan(mesh, T, cfg)
    lidar.write_npz(s, out / "scan.npz")
    lidar.write_ply(s, out / "scan.ply")
    figures.lidar_figure(s, out / "lidar_class.png", mesh.class_names, source.stem)
    counts = {str(c): int(n) for c, n in zip(*np.unique(s.class_id, return_counts=True), strict=True)}
    return {"rays": s.n_rays, "returns": len(s.range_m), "returns_per_class": counts}


def _write_sonar(mesh: LayeredMesh, cfg: sonar.SonarConfig, T: Rigid3, out: Path, source: Path) -> dict:
    img = sonar.ping(mesh, T, cfg)

    with atomic_path(out / "sonar.npz") as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, intensity=img.intensity, clean=img.clean, class_id=img.class_id,
                            ranges_m=img.ranges_m, bearings_rad=img.bearings_rad)
    write_image(out / "sonar_polar.png", sonar.to_uint8(img.intensity, cfg.dynamic_range_db)[::-1])
    figures.sonar_figure(img, out / "sonar.png", cfg.dynamic_range_db, mesh.class_names, source.stem)
    return {"cells_with_return": int((img.class_id >= 0).sum()), "peak_intensity": float(img.clean.max())}


def _write_view(mesh: LayeredMesh, cfg: views.ViewConfig, T: Rigid3, out: Path, source: Path) -> dict:
    v = views.render(mesh, cfg.camera(), T, max_range_m=cfg.max_range_m, engine_name=cfg.engine, device=cfg.device)
    _write_view_files(v, out, "")
    return {"hit_fraction": float((v.face >= 0).mean())}


def _write_view_files(v: views.ViewFrame, out: Path, prefix: str) -> None:
    write_image(out / f"{prefix}rgb.png", v.rgb)
    write_image(out / f"{prefix}class.png", figures.class_colours(v.class_id))
    if not prefix:
        write_image(out / "depth.png", np.clip(np.rint(v.depth_m * 1000), 0, 65535).astype(np.uint16))

        with atomic_path(out / "view.npz") as tmp, open(tmp, "wb") as fh:
            np.savez_compressed(fh, rgb=v.rgb, depth_m=v.depth_m, range_m=v.range_m, class_id=v.class_id,
                                part_id=v.part_id, pane_id=v.pane_id, face=v.face)


def _write_mesh(mesh: LayeredMesh, cfg: layered_mesh.LayeredMeshConfig, T: Rigid3 | None, out: Path,
                source: Path) -> dict:
    write_ply(mesh, out / "layered_mesh.ply")
    inp = read_image_input(source)  # for its camera only
    T_cam = Rigid3() if inp.T_world_from_cam is None else Rigid3.from_matrix(inp.T_world_from_cam)
    H, W = np.shape(inp.depth_m)

    v = views.render(mesh, Camera(inp.K, W, H), T_cam if T is None else T)
    _write_view_files(v, out, "preview_")
    return {"vertices": len(mesh.vertices_m), "panes": int(mesh.pane_id.max(initial=0))}


_WRITERS = {"lidar": _write_lidar, "sonar": _write_sonar, "view": _write_view, "mesh": _write_mesh}

"""GenLaM from a photo against exact truth, on simulator frames of a scene spec (issue 47's acceptance figures).

For each of ``frames`` trajectory poses (evenly spread over the clip) the CAD scene is rendered (exact rgb,
z-depth, classes) and:

* ``focal``: the exact point map, z-shifted by ``shift_m``, goes through eq. (1)
  (:func:`cadalign.emulate.photo_camera.fit_point_map`): relative focal error; again with i.i.d. Gaussian
  noise of ``noise_rel`` times the depth on every coordinate;
* ``scan``: the oracle photo (that point map, the true classes) -> eq. (1) camera -> layered mesh -> LiDAR
  scan, against the CAD scan with the same rays (:func:`cadalign.emulate.photo_eval.compare_with_cad`), from
  the camera's own pose and from a pose ``offset_m`` to its right;
* seconds for the mesh and the scan (and, with ``depth_model`` / ``seg_model``, for the networks on the
  rendered rgb; their accuracy there is not a claim about real photos).

Writes ``bench_photo.json``.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np

from cadalign.emulate import lidar
from cadalign.emulate.layered_mesh import ImageInput, mesh_from_image
from cadalign.emulate.photo import PhotoConfig, camera_lidar_pose
from cadalign.emulate.photo_camera import K_from_hfov, fit_point_map
from cadalign.emulate.photo_eval import compare_with_cad
from cadalign.emulate.pretrained import load_depth_model, load_seg_model
from cadalign.emulate.sources import scene_mesh
from cadalign.emulate.views import render
from cadalign.geometry import depth_to_points
from cadalign.io import write_json
from cadalign.sim.spec import load_scene
from cadalign.sim.trajectory import pose_at
from cadalign.types import Camera, Rigid3


def _frame(mesh, cam, T):  # noqa: ANN001

    return render(mesh, cam, T)


def bench_photo(scene_path: Path, out_dir: Path, *, frames: int = 4, width: int = 320, height: int = 240,
                hfov_deg: float = 60.0, shift_m: float = 0.8, noise_rel: float = 0.02, offset_m: float = 0.3,
                depth_model: Path | None = None, seg_model: Path | None = None, seed: int = 0) -> dict:
    """Run the measurements of the module docstring; returns and writes ``out_dir/bench_photo.json``."""

    spec = load_scene(Path(scene_path))
    cad = scene_mesh(Path(scene_path))
    cam = Camera(K_from_hfov(width, height, hfov_deg), width, height)
    cfg = PhotoConfig()
    scan_cfg = dataclasses.replace(cfg.scan, max_range_m=100.0)
    rng = np.random.default_rng(seed)
    nets = _networks(depth_model, seg_model)
    rows = []
    traj = spec.trajectory
    ks = np.linspace(0, traj.frames - 1, frames).round().astype(int)  # spread over the clip
    for T in (pose_at(traj, k / traj.fps, spec.seed) for k in ks):
        v = _frame(cad, cam, T)
        P, _ = depth_to_points(cam.K, v.depth_m)
        P[..., 2] -= shift_m
        f, dz, res = fit_point_map(P)
        Pn = P + noise_rel * (P[..., 2:] + shift_m) * rng.standard_normal(P.shape)
        fn, _, res_n = fit_point_map(Pn)
        K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
        depth = np.where(v.depth_m > 0, P[..., 2] + dz, 0.0)
        t = time.perf_counter()
        mesh = mesh_from_image(ImageInput(v.rgb, depth, K, class_id=v.class_id,
                                          T_world_from_cam=T.matrix()), cfg.mesh)
        mesh_s = time.perf_counter() - t
        T_l = T @ camera_lidar_pose()
        t = time.perf_counter()
        lidar.scan(mesh, T_l, scan_cfg)
        scan_s = time.perf_counter() - t
        same = compare_with_cad(mesh, cad, T_l, scan_cfg, cam, T, v.depth_m)
        moved = Rigid3(T_l.R, T_l.t + T.R @ [offset_m, 0.0, 0.0])
        off = compare_with_cad(mesh, cad, moved, scan_cfg, cam, T, v.depth_m)
        rows.append({"focal_err_exact": abs(f / cam.fx - 1), "residual_px_exact": res,
                     "focal_err_noisy": abs(fn / cam.fx - 1), "residual_px_noisy": res_n,
                     "same_pose": dataclasses.asdict(same), "moved": dataclasses.asdict(off),
                     "mesh_s": mesh_s, "scan_s": scan_s, "faces": mesh.n_faces} | nets(v.rgb))
    out = {"scene": str(scene_path), "size": [width, height], "hfov_deg": hfov_deg, "shift_m": shift_m,
           "noise_rel": noise_rel, "offset_m": offset_m, "scan": dataclasses.asdict(scan_cfg), "frames": rows}
    write_json(Path(out_dir) / "bench_photo.json", out)
    return out


def _networks(depth_model: Path | None, seg_model: Path | None):  # noqa: ANN202
    """A function timing the given checkpoints on one rgb (``{}`` when none is given)."""

    depth_fn = load_depth_model(depth_model) if depth_model is not None else None
    seg = load_seg_model(seg_model) if seg_model is not None else None

    def timed(rgb: np.ndarray) -> dict:
        out = {}
        if depth_fn is not None:
            t = time.perf_counter()
            depth_fn(rgb)
            out["depth_s"] = time.perf_counter() - t
        if seg is not None:
            t = time.perf_counter()
            seg.predict(rgb)
            out["classes_s"] = time.perf_counter() - t
        return out

    return timed

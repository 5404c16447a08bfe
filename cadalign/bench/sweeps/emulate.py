"""The emulation sweep: LiDAR resolution and ray-cast engine against time and agreement.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from cadalign.bench.data import BenchData
from cadalign.bench.framework import BenchConfig, Metric, Sweep, SweepPoint
from cadalign.emulate import lidar
from cadalign.emulate.lidar import LidarConfig
from cadalign.emulate.open3d_baseline import Open3DRaycast
from cadalign.emulate.raycast_engines import BVHEngine, TorchEngine
from cadalign.emulate.sources import scene_mesh
from cadalign.sim.spec import load_scene
from cadalign.sim.trajectory import pose_at
from cadalign.types import Rigid3

EMULATE_POINTS = {
    0: (("bvh", 8, 1.0), ("bvh", 16, 0.5), ("bvh", 32, 0.25), ("torch", 8, 1.0), ("torch", 16, 0.5)),
    1: (("bvh", 16, 1.0), ("bvh", 32, 0.5), ("bvh", 64, 0.25), ("bvh", 128, 0.125), ("torch", 16, 1.0),
        ("torch", 32, 0.5)),
    2: (("bvh", 16, 1.0), ("bvh", 32, 0.5), ("bvh", 64, 0.25), ("bvh", 128, 0.125), ("bvh", 256, 0.0625),
        ("torch", 16, 1.0), ("torch", 32, 0.5), ("torch", 64, 0.25)),
}


EMULATE_OPEN3D = "Open3D raycast alone"
"""Name (after the rays) of the emulate sweep's baseline setting: ``o3d.t.geometry.RaycastingScene.cast_rays`` on
the densest BVH setting's rays, nothing else (:class:`~cadalign.emulate.open3d_baseline.Open3DRaycast`)."""


def emulate_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """LiDAR rays (beams x azimuth step) and engine (BVH / torch): surface sampling gap vs seconds per scan; each
    setting's rays are also cast by Open3D alone in the same measurement, and Open3D alone on the densest BVH
    setting's rays is the sweep's baseline."""
    pts = EMULATE_POINTS[data.size.level]
    densest = max((p for p in pts if p[0] == "bvh"), key=lambda p: p[1] / p[2])
    # the reference is finer than every setting (twice the beams, half the azimuth step)
    ref_channels, ref_step = 2 * max(c for _, c, _ in pts), min(a for _, _, a in pts) / 2

    def lidar_cfg(channels: int, step: float):  # -> LidarConfig
        return LidarConfig(channels=channels, vfov_deg=(-45.0, 45.0), horizontal_res_deg=step, max_range_m=1000.0,
                           range_noise_m=0.0, seed=cfg.seed)

    def setup() -> dict[str, Any]:
        path = data.scene()
        spec = load_scene(path)
        mesh = scene_mesh(path)
        T = Rigid3(np.eye(3), pose_at(spec.trajectory, 0.0, spec.seed).t)
        ref = lidar.scan(mesh, T, lidar_cfg(ref_channels, ref_step), engine=BVHEngine(mesh.vertices_m, mesh.faces))
        pts = ref.xyz_world[np.random.default_rng(cfg.seed).permutation(len(ref.xyz_world))[:20_000]]
        return {"mesh": mesh, "T": T, "ref_pts": pts, "ref_hits": len(ref.xyz_world), "tree": cKDTree,
                "open3d": Open3DRaycast(mesh.vertices_m, mesh.faces)}

    def prepare(s: dict[str, Any], knobs: dict[str, Any]) -> tuple[Any, Any]:
        eng = (BVHEngine if knobs["engine"] == "bvh" else TorchEngine)(s["mesh"].vertices_m, s["mesh"].faces)
        c = lidar_cfg(knobs["channels"], knobs["azimuth_step_deg"])
        return eng, (c, lidar.scan_directions(c))

    def measure(s: dict[str, Any], knobs: dict[str, Any], prep: tuple[Any, Any]) -> dict[str, float]:
        eng, (c, pattern) = prep
        d_world = pattern[0] @ s["T"].R.T
        t0 = time.perf_counter()
        o3d_pts = s["open3d"].hit_points(s["T"].t, d_world)  # the same rays, Open3D alone
        o3d_s = time.perf_counter() - t0
        if knobs.get("open3d_alone"):
            sec, xyz, n_rays = o3d_s, o3d_pts, len(d_world)
        else:
            t0 = time.perf_counter()
            sc = lidar.scan(s["mesh"], s["T"], c, engine=eng, pattern=pattern)
            sec, xyz, n_rays = time.perf_counter() - t0, sc.xyz_world, sc.n_rays
        gap = s["tree"](xyz).query(s["ref_pts"])[0] if len(xyz) else np.full(1, np.inf)
        # the baseline's gap under another key: with no classes, colours or noise it is not a setting one would
        # pick, so it is never on the Pareto front nor recommended, only the cost every setting is divided by
        gap_key = "open3d_gap_m" if knobs.get("open3d_alone") else "gap_m"
        return {"scan_s": sec, "rays": float(n_rays), "rays_per_s": n_rays / sec, "returns": float(len(xyz)),
                gap_key: float(np.mean(gap)), "open3d_s": o3d_s, "cost_vs_open3d": sec / o3d_s}

    points = [SweepPoint(f"{e} {c}x{360 / a:g}", {"engine": e, "channels": c, "azimuth_step_deg": a})
              for e, c, a in pts]
    _, c, a = densest
    points.append(SweepPoint(f"{c}x{360 / a:g} {EMULATE_OPEN3D}",
                             {"engine": "bvh", "channels": c, "azimuth_step_deg": a, "open3d_alone": True}))
    return Sweep(
        "emulate", tuple(points),
        Metric("gap_m", "surface gap: mean distance from a dense scan to the nearest return (m)"),
        Metric("scan_s", "seconds per LiDAR scan"), measure, setup, prepare=prepare, baseline=points[-1].name,
        description=(f"Spinning LiDAR (+-45 deg elevation, beams x azimuth steps) of the default scene from the first "
                     f"camera position, BVH (Open3D/Embree) vs the exact torch engine; accuracy: how finely the "
                     f"returns sample the surface, against a {ref_channels}x{360 / ref_step:g} BVH scan "
                     "(both engines are exact: same rays give the same gap, only the time differs). "
                     f"'{EMULATE_OPEN3D}' is Open3D's RaycastingScene casting the densest BVH setting's rays and "
                     "nothing else; the table's cost ratio divides each setting's seconds by its seconds, and each "
                     "record's cost_vs_open3d by Open3D alone on the setting's own rays, timed in the same "
                     "measurement."))

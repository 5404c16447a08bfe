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


def emulate_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """LiDAR rays (beams x azimuth step) and engine (BVH / torch): surface sampling gap vs seconds per scan."""
    pts = EMULATE_POINTS[data.size.level]
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
        return {"mesh": mesh, "T": T, "ref_pts": pts, "ref_hits": len(ref.xyz_world), "tree": cKDTree}

    def prepare(s: dict[str, Any], knobs: dict[str, Any]) -> tuple[Any, Any]:
        eng = (BVHEngine if knobs["engine"] == "bvh" else TorchEngine)(s["mesh"].vertices_m, s["mesh"].faces)
        c = lidar_cfg(knobs["channels"], knobs["azimuth_step_deg"])
        return eng, (c, lidar.scan_directions(c))

    def measure(s: dict[str, Any], knobs: dict[str, Any], prep: tuple[Any, Any]) -> dict[str, float]:
        eng, (c, pattern) = prep
        t0 = time.perf_counter()
        sc = lidar.scan(s["mesh"], s["T"], c, engine=eng, pattern=pattern)
        sec = time.perf_counter() - t0
        gap = s["tree"](sc.xyz_world).query(s["ref_pts"])[0] if len(sc.xyz_world) else np.full(1, np.inf)
        return {"scan_s": sec, "rays": float(sc.n_rays), "rays_per_s": sc.n_rays / sec,
                "returns": float(len(sc.range_m)), "gap_m": float(np.mean(gap))}

    return Sweep(
        "emulate", tuple(SweepPoint(f"{e} {c}x{360 / a:g}", {"engine": e, "channels": c, "azimuth_step_deg": a})
                         for e, c, a in pts),
        Metric("gap_m", "surface gap: mean distance from a dense scan to the nearest return (m)"),
        Metric("scan_s", "seconds per LiDAR scan"), measure, setup, prepare=prepare,
        description=(f"Spinning LiDAR (+-45 deg elevation, beams x azimuth steps) of the default scene from the first "
                     f"camera position, BVH (Open3D/Embree) vs the exact torch engine; accuracy: how finely the "
                     f"returns sample the surface, against a {ref_channels}x{360 / ref_step:g} BVH scan "
                     "(both engines are exact: same rays give the same gap, only the time differs)."))

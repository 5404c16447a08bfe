"""Ray-casting throughput and agreement of the two emulation engines on a scene (default: the default scene).

Measured in one run, on the same mesh and the same rays:

* ``bvh_cast``: Open3D BVH, rays/s of the cast alone on a 1M-ray spinning pattern (256 rings x 4096 azimuths);
* ``bvh_scan``: the whole 1M-ray LiDAR scan (:func:`cadalign.emulate.lidar.scan`: ray generation, rotation,
  cast, range window, noise, colour/class/part lookup) in seconds;
* ``torch``: rays/s of the exact Möller–Trumbore engine on a contiguous block of the same rays;
* ``agreement``: both engines on uniform-sphere rays from the trajectory's first poses: the share of rays
  where both miss, or both hit within ``tol_m`` of each other, and the share of common hits of equal class.

Timings are minima over ``rounds`` (noise on a shared machine only adds time). Each also has its process CPU
time (all threads): on a machine shared by other jobs, ``cpu_s / cores`` estimates the wall time on idle cores.
Writes ``bench_emulate.json``.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np

from cadalign.emulate import lidar
from cadalign.emulate.raycast_engines import BVHEngine, TorchEngine
from cadalign.emulate.sources import scene_mesh
from cadalign.io import write_json
from cadalign.sim.spec import load_scene
from cadalign.sim.trajectory import frame_poses
from cadalign.types import Rigid3

log = logging.getLogger(__name__)


def _best(fn, rounds: int) -> tuple[float, float]:  # noqa: ANN001
    """Minimum wall-clock and minimum process CPU seconds (all threads) of ``fn`` over ``rounds`` calls."""
    wall, cpu = np.inf, np.inf
    for _ in range(rounds):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall, cpu = min(wall, time.perf_counter() - t), min(cpu, time.process_time() - c)
    return float(wall), float(cpu)


def agreement(mesh, origins: np.ndarray, dirs: np.ndarray, tol_m: float = 1e-4) -> dict:  # noqa: ANN001
    """Hit/range/class agreement of the BVH and torch engines on rays ``(N, 3)`` from ``origins``."""

    a = BVHEngine(mesh.vertices_m, mesh.faces).cast(origins, dirs)
    b = TorchEngine(mesh.vertices_m, mesh.faces).cast(origins, dirs)
    both = a.hit & b.hit
    diff = np.zeros(len(dirs))
    diff[both] = np.abs(a.range_m[both] - b.range_m[both])
    agree = (a.hit == b.hit) & (diff <= tol_m)
    same_class = mesh.class_id[a.face[both]] == mesh.class_id[b.face[both]]
    return {"rays": len(dirs), "hits": int(a.hit.sum()), "agree_fraction": float(agree.mean()),
            "hit_mismatch": int((a.hit != b.hit).sum()), "range_max_diff_m": float(diff.max(initial=0)),
            "class_agree_fraction": float(same_class.mean()) if both.any() else 1.0, "tol_m": tol_m}


def bench_emulate(scene_path: Path, out_dir: Path, *, rings: int = 256, azimuths: int = 4096,
                  torch_rays: int = 20_000, agree_rays: int = 100_000, rounds: int = 10, poses: int = 4,
                  torch_threads: tuple[int, ...] = (1, 2)) -> dict:
    """Time and compare the engines on ``scene_path``; writes ``out_dir/bench_emulate.json`` and returns it.

    The timed scan has ``rings x azimuths`` rays (default 1,048,576) over +-45 degrees of elevation.
    The torch engine is timed once per CPU thread count in ``torch_threads`` (torch's setting is restored).
    """
    import torch  # lazy: heavy dependency (torch)

    spec = load_scene(Path(scene_path))
    mesh = scene_mesh(Path(scene_path))
    cams = frame_poses(spec.trajectory, spec.trajectory.frames, spec.seed)
    T = Rigid3(np.eye(3), cams[0].t)
    cfg = lidar.LidarConfig(channels=rings, vfov_deg=(-45.0, 45.0), horizontal_res_deg=360 / azimuths,
                            max_range_m=1000.0, range_noise_m=0.01)
    pattern = lidar.scan_directions(cfg)  # fixed per sensor, built once
    d = pattern[0]
    bvh = BVHEngine(mesh.vertices_m, mesh.faces)
    origins = np.broadcast_to(T.t, d.shape)
    cast_s, cast_cpu = _best(lambda: bvh.cast_unit(origins, d), rounds)
    scan_s, scan_cpu = _best(lambda: lidar.scan(mesh, T, cfg, engine=bvh, pattern=pattern), rounds)
    te = TorchEngine(mesh.vertices_m, mesh.faces)
    start = len(d) // 3  # a block of columns that sees the structure and the seabed
    block = d[start:start + torch_rays]
    threads = torch.get_num_threads()
    torch_runs = {}
    try:
        for n in torch_threads:
            torch.set_num_threads(n)
            wall, cpu = _best(lambda: te.cast_unit(T.t, block), 3)
            torch_runs[str(n)] = {"s": wall, "cpu_s": cpu, "rays_per_s": len(block) / wall,
                                  "rays_per_cpu_s": len(block) / cpu}
    finally:
        torch.set_num_threads(threads)
    rng = np.random.default_rng(0)
    per = agree_rays // poses
    o_all = np.concatenate([np.tile(c.t, (per, 1)) for c in cams[:: max(1, len(cams) // poses)][:poses]])
    agree = agreement(mesh, o_all, lidar.uniform_sphere(len(o_all), rng))
    result = {
        "scene": str(scene_path), "faces": mesh.n_faces, "rays": len(d),
        "bvh_cast_s": cast_s, "bvh_cast_rays_per_s": len(d) / cast_s, "bvh_cast_cpu_s": cast_cpu,
        "bvh_scan_s": scan_s, "bvh_scan_rays_per_s": len(d) / scan_s, "bvh_scan_cpu_s": scan_cpu,
        "torch_rays": len(block), "torch_by_threads": torch_runs, "cpu_count": os.cpu_count(),
        "load_avg_1min": os.getloadavg()[0], "agreement": agree,
    }
    write_json(Path(out_dir) / "bench_emulate.json", result)
    log.info("BVH %.3f s cast / %.3f s scan per %d rays; torch %s; agreement %.5f",
             cast_s, scan_s, len(d), torch_runs, agree["agree_fraction"])
    return result


if __name__ == "__main__":  # OMP_NUM_THREADS=1 python -m cadalign.bench.emulate [SCENE] [OUT]
    import json
    import sys

    from cadalign.sim.spec import default_scene_path

    args = sys.argv[1:]
    res = bench_emulate(Path(args[0]) if args else default_scene_path(),
                        Path(args[1]) if len(args) > 1 else Path("runs/bench/emulate"))
    print(json.dumps(res, indent=2))

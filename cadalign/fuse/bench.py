"""Throughput of fusion (frames/s), for ``cadalign bench fuse``: frames are read first, then only
``integrate`` (TSDF/surfels + the semantic update) is timed, per frame, wall clock and process CPU time."""

from __future__ import annotations

import platform
import time
from pathlib import Path

import numpy as np

from cadalign.config import to_dict
from cadalign.fuse.config import FuseConfig
from cadalign.fuse.inputs import open_source
from cadalign.fuse.map_io import new_map
from cadalign.io import write_json


def bench_fuse(source: Path, cfg: FuseConfig, *, frames: int = 32, warmup: int = 2, out: Path | None = None) -> dict:
    """Fuse the first ``frames`` frames of ``source`` (GT depth and labels) and time each ``integrate``.

    Returns (and writes to ``out/bench_fuse.json`` when given) frames/s from the median and the mean wall time
    per frame, the CPU time per frame (wall time inflated by other processes shows as wall >> CPU / threads),
    the split between geometry and labels, and the image size.
    """
    src = open_source(source, label_confidence=cfg.label_confidence, max_frames=frames + warmup)
    loaded = [src.frame(i) for i in src.ids]
    m = new_map(cfg, src.n_classes)
    wall, cpu = [], []
    for k, frame in enumerate(loaded):
        if k == warmup:
            m.seconds = dict.fromkeys(m.seconds, 0.0)
        t0, c0 = time.perf_counter(), time.process_time()
        m.integrate(frame)
        if k >= warmup:
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
    wall_a = np.array(wall)
    cam = loaded[0].camera
    result = {
        "method": cfg.method, "voxel_m": cfg.voxel_m, "image": f"{cam.width}x{cam.height}", "frames_timed": len(wall),
        "frames_per_second_median": float(1.0 / np.median(wall_a)),
        "frames_per_second_mean": float(1.0 / wall_a.mean()),
        "ms_per_frame_median": float(1000 * np.median(wall_a)), "cpu_ms_per_frame_median": float(1000 * np.median(cpu)),
        "seconds_by_part": {k: v / max(len(wall), 1) for k, v in m.seconds.items()},
        "config": to_dict(cfg), "source": str(src.scene.dir), "machine": platform.processor() or platform.machine(),
    }
    if out is not None:
        write_json(Path(out) / "bench_fuse.json", result)
    return result

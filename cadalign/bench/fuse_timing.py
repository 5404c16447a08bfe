"""Throughput of fusion (frames/s), for ``cadalign bench fuse`` and the lead's idle-machine runs.

Frames are read first; then only ``integrate`` (TSDF/surfels + the semantic update) is timed, per frame, in
wall-clock and process CPU time. The configuration under test and a *baseline* (by default the same
configuration with the speed knobs of the first implementation, see :func:`baseline_of`) are fused
frame by frame in alternation, so both see the same machine load and their ratio is meaningful on a shared
machine even when the absolute numbers are not. The 1-minute load average before and after is recorded:
with more runnable processes than cores, wall time says more about the neighbours than about the code,
and CPU time per frame (which counts every thread of this process) is the steadier number.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from cadalign.config import to_dict
from cadalign.fuse.base import FuseFrame, LabelledGeometry, SemanticMap, origin_from_frame, valid_depth
from cadalign.fuse.config import FuseConfig
from cadalign.fuse.inputs import open_source
from cadalign.fuse.map_io import new_map
from cadalign.fuse.tsdf import require_open3d
from cadalign.io import write_json
from cadalign.types import Rigid3

OPEN3D = "open3d"
"""Name of the Open3D-alone timing in :func:`bench_fuse`'s result and :func:`time_interleaved`'s maps."""


class Open3DTSDF:
    """Open3D's ``VoxelBlockGrid`` alone (``tsdf``, ``weight``, ``color``; no labels, no weight cap): the
    reference cost of geometry, timed beside the semantic map. Each frame is what Open3D's own examples do:
    ``compute_unique_block_coordinates`` then ``integrate`` (depth and colour), with ``cfg``'s voxel size,
    block size, initial block count, truncation and depth range."""

    def __init__(self, cfg: FuseConfig) -> None:
        o3d = require_open3d()
        self.cfg, self.o3d = cfg, o3d
        f32 = o3d.core.float32
        self.vbg = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight", "color"), (f32,) * 3, ((1,), (1,), (3,)),
                                                 float(cfg.voxel_m), int(cfg.block_resolution),
                                                 int(cfg.block_count), o3d.core.Device("CPU:0"))
        self.origin: np.ndarray | None = None
        self.seconds = {"tsdf": 0.0}
        self.frames_integrated = 0

    def integrate(self, frame: FuseFrame) -> None:
        o3d, cfg = self.o3d, self.cfg
        t0 = time.perf_counter()
        mask = valid_depth(frame.depth_m, cfg.depth_min_m, cfg.depth_max_m)
        if self.origin is None:
            self.origin = origin_from_frame(frame, mask, cfg.voxel_m * cfg.block_resolution)
        K = o3d.core.Tensor(frame.camera.K)
        E = o3d.core.Tensor((frame.T_cam_from_world @ Rigid3(np.eye(3), self.origin)).matrix())
        depth = o3d.t.geometry.Image(o3d.core.Tensor(np.where(mask, frame.depth_m, 0).astype(np.float32)))
        rgb = frame.rgb if frame.rgb is not None else np.full((*mask.shape, 3), 128, np.uint8)
        color = o3d.t.geometry.Image(o3d.core.Tensor(np.ascontiguousarray(rgb, dtype=np.float32) / 255.0))
        args = (1.0, float(cfg.depth_max_m), float(cfg.trunc_voxels))
        coords = self.vbg.compute_unique_block_coordinates(depth, K, E, *args)
        self.vbg.integrate(coords, depth, color, K, E, *args)
        self.seconds["tsdf"] += time.perf_counter() - t0
        self.frames_integrated += 1

    def extract_mesh(self, n_classes: int) -> LabelledGeometry:
        """The zero level set (world coordinates), every vertex class 0 with uniform probabilities (no labels)."""
        mesh = self.vbg.extract_triangle_mesh(weight_threshold=max(float(self.cfg.mesh_weight_threshold) - 0.5, 0.0))
        pos = mesh.vertex.positions.numpy().astype(np.float64) + self.origin
        n = len(pos)
        return LabelledGeometry(pos, np.zeros((n, 3), np.float32), np.full((n, 3), 128, np.uint8),
                                np.zeros(n, np.int64), np.full((n, n_classes), 1 / n_classes, np.float32),
                                mesh.triangle.indices.numpy().astype(np.int64))


def baseline_of(cfg: FuseConfig) -> FuseConfig:
    """The configuration the speed-up is measured against: ``cfg`` with every speed knob back at the first
    implementation's defaults (reference label path, 8^3 blocks, colour on every frame, labels from every
    pixel); the initial block count is scaled with the block area so both tables hold about the same surface."""
    scale = (cfg.block_resolution / 8) ** 2
    return dataclasses.replace(cfg, label_lookup="reference", block_resolution=8, color_every=1, label_pixel_stride=1,
                               block_count=max(16, round(cfg.block_count * scale)))


@dataclass
class PathTiming:
    """Per-frame times of one configuration (warm-up frames excluded)."""

    wall_s: list[float] = field(default_factory=list)
    cpu_s: list[float] = field(default_factory=list)
    parts_s: dict[str, float] = field(default_factory=dict)
    """Seconds per part (the map's ``seconds``: ``tsdf``/``labels`` or the surfel steps), summed."""
    parts_cpu_s: dict[str, float] = field(default_factory=dict)
    """Process CPU seconds per part where the map records them (``cpu_seconds``), summed."""

    def summary(self) -> dict[str, float | dict[str, float]]:
        """ms per frame (median, mean), frames/s (from both), CPU ms per frame (median), ms per part (mean)."""
        wall, n = np.asarray(self.wall_s), max(len(self.wall_s), 1)
        return {
            "ms_per_frame_median": float(1000 * np.median(wall)), "ms_per_frame_mean": float(1000 * wall.mean()),
            "frames_per_second_median": float(1 / np.median(wall)), "frames_per_second_mean": float(1 / wall.mean()),
            "cpu_ms_per_frame_median": float(1000 * np.median(self.cpu_s)),
            "ms_by_part": {k: 1000 * v / n for k, v in self.parts_s.items()},
            "cpu_ms_by_part": {k: 1000 * v / n for k, v in self.parts_cpu_s.items()},
        }


def time_interleaved(frames: list[FuseFrame], n_classes: int, cfgs: dict[str, FuseConfig | Open3DTSDF], *,
                     warmup: int = 2) -> tuple[dict[str, PathTiming], dict[str, SemanticMap | Open3DTSDF]]:
    """Fuse ``frames`` into one new map per configuration (or into the given :class:`Open3DTSDF`), alternating
    them frame by frame (and their order every frame); returns the timings (the first ``warmup`` frames
    untimed) and the maps."""
    maps = {name: new_map(c, n_classes) if isinstance(c, FuseConfig) else c for name, c in cfgs.items()}
    timings = {name: PathTiming() for name in cfgs}
    names = list(cfgs)
    for k, frame in enumerate(frames):
        for name in names if k % 2 == 0 else names[::-1]:
            m = maps[name]
            if k == warmup:
                m.seconds = dict.fromkeys(m.seconds, 0.0)
                if hasattr(m, "cpu_seconds"):
                    m.cpu_seconds = dict.fromkeys(m.cpu_seconds, 0.0)
            t0, c0 = time.perf_counter(), time.process_time()
            m.integrate(frame)
            if k >= warmup:
                timings[name].wall_s.append(time.perf_counter() - t0)
                timings[name].cpu_s.append(time.process_time() - c0)
    for name, m in maps.items():
        timings[name].parts_s = dict(m.seconds) if len(frames) > warmup else {}
        timings[name].parts_cpu_s = dict(getattr(m, "cpu_seconds", {})) if len(frames) > warmup else {}
    return timings, maps


def load_average() -> float:
    """The 1-minute load average (runnable processes), NaN where the platform has none."""
    try:
        return float(os.getloadavg()[0])
    except OSError:
        return float("nan")


def _open3d_threads() -> int | None:
    o3d = require_open3d()
    return int(o3d.utility.get_max_threads()) if hasattr(o3d.utility, "get_max_threads") else None


def bench_fuse(source: Path, cfg: FuseConfig, *, frames: int = 32, warmup: int = 2,
               baseline: FuseConfig | None = None, out: Path | None = None) -> dict:
    """Fuse the first ``frames`` frames of ``source`` (GT depth and labels) with ``cfg``, with ``baseline``
    (default :func:`baseline_of` ``cfg``) and with Open3D's VoxelBlockGrid alone (:class:`Open3DTSDF`, no
    labels), interleaved, and time each ``integrate``.

    Returns (and writes to ``out/bench_fuse.json`` when given) for each: ms per frame and frames/s (median and
    mean wall time), CPU ms per frame, ms per part; the speed-up (baseline ms / ms, wall and CPU, medians);
    ``fps_vs_open3d``: frames/s of ``cfg`` over Open3D's alone (medians; ``_mean``: from mean times);
    the load average before and after; the CPU count, image size and both configs.
    """
    baseline = baseline if baseline is not None else baseline_of(cfg)
    src = open_source(source, label_confidence=cfg.label_confidence, max_frames=frames + warmup)
    loaded = [src.frame(i) for i in src.ids]
    load_before = load_average()
    timings, _ = time_interleaved(loaded, src.n_classes, {"new": cfg, "baseline": baseline, OPEN3D: Open3DTSDF(cfg)},
                                  warmup=warmup)
    new, base, o3d_alone = (timings[k].summary() for k in ("new", "baseline", OPEN3D))
    cam = loaded[0].camera
    result = {
        "method": cfg.method, "voxel_m": cfg.voxel_m, "image": f"{cam.width}x{cam.height}",
        "frames_timed": len(timings["new"].wall_s), **new,
        "seconds_by_part": {k: v / 1000 for k, v in new["ms_by_part"].items()},
        "baseline": base,
        "speedup_wall": base["ms_per_frame_median"] / new["ms_per_frame_median"],
        "speedup_cpu": base["cpu_ms_per_frame_median"] / max(new["cpu_ms_per_frame_median"], 1e-9),
        OPEN3D: o3d_alone,
        "fps_vs_open3d": o3d_alone["ms_per_frame_median"] / new["ms_per_frame_median"],
        "fps_vs_open3d_mean": o3d_alone["ms_per_frame_mean"] / new["ms_per_frame_mean"],
        "load_average_before": load_before, "load_average_after": load_average(), "cpu_count": os.cpu_count(),
        "open3d_threads": _open3d_threads(),
        "config": to_dict(cfg), "baseline_config": to_dict(baseline), "source": str(src.scene.dir),
        "machine": platform.processor() or platform.machine(),
    }
    if out is not None:
        write_json(Path(out) / "bench_fuse.json", result)
    return result

"""The fusion sweep: voxel size and method against map accuracy and time, beside Open3D's grid alone.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from cadalign.bench.data import BenchData
from cadalign.bench.framework import BenchConfig, Metric, Sweep, SweepPoint
from cadalign.bench.fuse_timing import OPEN3D, Open3DTSDF, baseline_of, load_average, time_interleaved
from cadalign.fuse.config import PRESETS
from cadalign.fuse.inputs import open_source
from cadalign.fuse.run import evaluate

FUSE_VOXELS = {0: (0.16, 0.08, 0.04), 1: (0.08, 0.04, 0.02), 2: (0.08, 0.04, 0.03, 0.02)}
"""Voxel sizes per size level (2 cm on the 320x240 clip already peaks at ~3 GB RSS; 1 cm would not fit 2 cores'
worth of shared memory)."""


FUSE_OPEN3D = "Open3D VBG alone"
"""Name (after the voxel size) of the fuse sweep's baseline setting: Open3D's VoxelBlockGrid without labels."""


def fuse_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """TSDF voxel size (and the ``realtime`` preset at the finest size): Chamfer distance to the CAD (and
    label accuracy) vs ms per fused frame, with the first implementation and Open3D's VoxelBlockGrid alone
    (no labels) timed in the same run; the latter is also the sweep's baseline setting."""
    finest = min(FUSE_VOXELS[data.size.level])
    points = [SweepPoint(f"{100 * v:g} cm", {"voxel_m": v}) for v in FUSE_VOXELS[data.size.level]]
    if data.size.level >= 1:
        points.append(SweepPoint(f"{100 * finest:g} cm realtime", {"voxel_m": finest, "preset": "realtime"}))
    # the reference cost: Open3D's VoxelBlockGrid alone (no labels) at the finest size; the table divides every
    # setting's ms by its ms (``cost / ...``), and each setting's record also holds the ratio timed interleaved
    points.append(SweepPoint(f"{100 * finest:g} cm {FUSE_OPEN3D}", {"voxel_m": finest, "open3d_alone": True}))

    def setup() -> Any:
        src = open_source(data.clip())
        return src, [src.frame(i) for i in src.ids]

    w, h = data.size.clip_resolution
    return Sweep(
        "fuse", tuple(points), Metric("chamfer_m", "Chamfer distance to the visible CAD (m)"),
        Metric("ms_per_frame", "ms per integrated frame"),
        lambda shared, knobs, _: fuse_measure(shared, knobs, cfg.seed), setup, baseline=points[-1].name,
        description=(f"Semantic TSDF fusion of the clip's exact depth and labels ({data.size.clip_frames} frames "
                     f"at {w}x{h}) at each voxel size, and the realtime preset (4^3 blocks, colour every 4th frame, "
                     "labels from every 2nd pixel) at the finest; time is integrate() only (frames/s, ms per part "
                     "and CPU ms in the table), interleaved frame by frame with the first implementation "
                     "(reference label path, 8^3 blocks, colour every frame) for the speed-up and with Open3D's "
                     "VoxelBlockGrid alone (no labels; fps_vs_open3d = its ms over the setting's), with the 1-minute "
                     f"load average. '{FUSE_OPEN3D}' is that Open3D grid as a setting of its own (no accuracy "
                     "shown: it has no labels; its Chamfer is open3d_chamfer_m): the table's cost ratio divides "
                     "each setting's ms by its ms. Accuracy: the truncated Chamfer distance "
                     "between the fused mesh and the visible CAD surface."))


def fuse_measure(shared: tuple[Any, list[Any]], knobs: dict[str, Any], seed: int) -> dict[str, float]:
    """One fuse setting: the map and its metrics, and its timing against :func:`~cadalign.bench.fuse_timing.baseline_of`
    and :class:`~cadalign.bench.fuse_timing.Open3DTSDF` on the same frames (``shared`` = (FrameSource, loaded frames));
    with ``open3d_alone`` in ``knobs``, Open3D's grid alone and its mesh's metrics."""

    src, frames = shared
    fc = dataclasses.replace(PRESETS[knobs.get("preset", "default")], voxel_m=knobs["voxel_m"])
    load = load_average()
    if knobs.get("open3d_alone"):
        timings, maps = time_interleaved(frames, src.n_classes, {OPEN3D: Open3DTSDF(fc)}, warmup=0)
        t = timings[OPEN3D].summary()
        mesh = maps[OPEN3D].extract_mesh(src.n_classes)
        met = evaluate(src, fc, mesh, mesh, seed=seed)
        return {"ms_per_frame": t["ms_per_frame_mean"], "frames_per_s": t["frames_per_second_mean"],
                "ms_tsdf": t["ms_by_part"]["tsdf"], "cpu_ms_per_frame": 1000 * float(np.mean(timings[OPEN3D].cpu_s)),
                # its Chamfer under another key: no accuracy on the plot's axis, so the baseline (no labels) is
                # never on the Pareto front nor recommended, only the cost every setting is divided by
                "load_average": (load + load_average()) / 2, "open3d_chamfer_m": met["chamfer_m"],
                "completeness_within_5cm": met.get("completeness_within_5cm", float("nan"))}
    timings, maps = time_interleaved(frames, src.n_classes, {"new": fc, "old": baseline_of(fc), OPEN3D: Open3DTSDF(fc)},
                                     warmup=0)
    del maps["old"], maps[OPEN3D]  # free the baselines' blocks before the extraction
    new, old, o3d_alone = (timings[k].summary() for k in ("new", "old", OPEN3D))
    m = maps["new"]
    met = evaluate(src, fc, m.extract_mesh(), m.extract_points(), seed=seed)
    return {"ms_per_frame": new["ms_per_frame_mean"], "frames_per_s": new["frames_per_second_mean"],
            "ms_tsdf": new["ms_by_part"]["tsdf"], "ms_labels": new["ms_by_part"]["labels"],
            "cpu_ms_per_frame": 1000 * float(np.mean(timings["new"].cpu_s)),
            "old_ms_per_frame": old["ms_per_frame_mean"],
            "speedup_vs_old": old["ms_per_frame_mean"] / new["ms_per_frame_mean"],
            "speedup_cpu_vs_old": float(np.sum(timings["old"].cpu_s) / max(np.sum(timings["new"].cpu_s), 1e-9)),
            "open3d_ms_per_frame": o3d_alone["ms_per_frame_mean"],
            "fps_vs_open3d": o3d_alone["ms_per_frame_mean"] / new["ms_per_frame_mean"],
            "load_average": (load + load_average()) / 2, "chamfer_m": met["chamfer_m"],
            "label_accuracy": met.get("label_accuracy", float("nan")),
            "completeness_within_5cm": met.get("completeness_within_5cm", float("nan"))}

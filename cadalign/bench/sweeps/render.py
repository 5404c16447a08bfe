"""The ray-cast ground-truth sweep: renderer settings against time per frame.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from cadalign.bench.data import BenchData
from cadalign.bench.framework import BenchConfig, Metric, Sweep, SweepPoint
from cadalign.bench.sweeps.sim import frame_picks
from cadalign.sim.render import GroundTruthCaster
from cadalign.sim.scene import build_scene
from cadalign.sim.spec import load_scene
from cadalign.sim.trajectory import frame_poses

RENDER_RES = {0: ((40, 30), (80, 60), (160, 120)), 1: ((80, 60), (160, 120), (320, 240), (640, 480)),
              2: ((80, 60), (160, 120), (320, 240), (640, 480), (1280, 960))}


def render_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """Ray-cast ground truth at several resolutions: time per frame vs label agreement with a finer render."""
    res = RENDER_RES[data.size.level]
    ref_res = (2 * res[-1][0], 2 * res[-1][1])
    n_frames = (2, 3, 4)[data.size.level]

    def caster_at(width: int, height: int):  # -> GroundTruthCaster
        path = data.scene()
        return GroundTruthCaster(build_scene(load_scene(path), path, width=width, height=height))

    def setup() -> dict[str, Any]:
        spec = load_scene(data.scene())
        poses = [frame_poses(spec.trajectory, spec.trajectory.frames, spec.seed)[k]
                 for k in frame_picks(spec.trajectory.frames, n_frames)]
        ref = caster_at(*ref_res)
        return {"poses": poses, "ref": [ref.cast(T, with_full_masks=False) for T in poses]}

    def measure(s: dict[str, Any], knobs: dict[str, Any], caster: Any) -> dict[str, float]:
        secs, agree, rel = [], [], []
        for T, ref in zip(s["poses"], s["ref"], strict=True):
            t0 = time.perf_counter()
            gt = caster.cast(T)
            secs.append(time.perf_counter() - t0)
            f = ref_res[0] // knobs["width"]
            cls = np.repeat(np.repeat(gt.class_id, f, axis=0), f, axis=1)
            dep = np.repeat(np.repeat(gt.depth_m, f, axis=0), f, axis=1)
            agree.append(float(np.mean(cls == ref.class_id)))
            both = (dep > 0) & (ref.depth_m > 0)
            rel.append(float(np.mean(np.abs(dep[both] - ref.depth_m[both]) / ref.depth_m[both])) if both.any() else 0)
        return {"ms_per_frame": 1000 * float(np.median(secs)), "label_agreement": float(np.mean(agree)),
                "depth_abs_rel": float(np.mean(rel)), "pixels": float(knobs["width"] * knobs["height"])}

    return Sweep(
        "render", tuple(SweepPoint(f"{w}x{h}", {"width": w, "height": h}) for w, h in res),
        Metric("label_agreement", "class-label agreement with a 2x finer render", True),
        Metric("ms_per_frame", "ms per frame (depth, normals, classes, full masks)"), measure, setup,
        prepare=lambda s, k: caster_at(k["width"], k["height"]),
        description=(f"Exact ray-cast ground truth (Open3D) of the default scene at each resolution, {n_frames} "
                     f"poses. Accuracy: the low-resolution class map, upsampled (nearest), against a "
                     f"{ref_res[0]}x{ref_res[1]} render: what resolution costs in label detail at object edges."))

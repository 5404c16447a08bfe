"""The simulator sweep: water effects on or off, seconds per frame of the production path against fidelity to the
all-effects image.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from cadalign.bench.data import BenchData
from cadalign.bench.framework import BenchConfig, Metric, Sweep, SweepPoint
from cadalign.sim.effects_chain import build_chain
from cadalign.sim.render import GroundTruthCaster, RGBRenderer
from cadalign.sim.run import apply_overrides, render_frame
from cadalign.sim.scene import build_scene
from cadalign.sim.spec import load_scene

SIM_VARIANTS: dict[str, tuple[str, ...]] = {
    "none": (),
    "water": ("attenuation", "backscatter"),
    "water+lamps": ("artificial_light", "attenuation", "backscatter", "vignetting"),
    "no_snow_noise": ("artificial_light", "attenuation", "forward_scatter", "backscatter", "motion_blur",
                      "vignetting"),
    "all": ("artificial_light", "attenuation", "forward_scatter", "backscatter", "marine_snow", "motion_blur",
            "vignetting", "low_light"),
}
"""Effect subsets of the sim sweep (kept in the simulator's pipeline order)."""


def frame_picks(n_total: int, n: int) -> list[int]:
    return [int(k) for k in np.linspace(0, n_total - 1, min(n, n_total)).round()]


def sim_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """Effects on/off: seconds per frame of the production path vs fidelity to the all-effects image."""
    n_frames = (2, 4, 8)[data.size.level]

    def setup() -> dict[str, Any]:
        path = data.scene()
        spec = apply_overrides(load_scene(path), None, data.size.clip_resolution, cfg.seed)
        scene = build_scene(spec, path)
        renderer, caster = RGBRenderer(scene), GroundTruthCaster(scene)
        ids = frame_picks(spec.trajectory.frames, n_frames)
        ref = {k: np.clip(render_frame(scene, build_chain(spec), k, renderer, caster)[1], 0, 1) for k in ids}
        return {"scene": scene, "renderer": renderer, "caster": caster, "ids": ids, "ref": ref}

    def prepare(s: dict[str, Any], knobs: dict[str, Any]) -> tuple[Any, Any]:
        scene = s["scene"]
        effects = tuple(knobs["effects"])
        spec = dataclasses.replace(scene.spec, effects=effects,
                                   effect_params={k: v for k, v in scene.spec.effect_params.items() if k in effects})
        variant, chain = dataclasses.replace(scene, spec=spec), build_chain(spec)
        render_frame(variant, chain, s["ids"][0], s["renderer"], s["caster"])  # warm-up, not timed
        return variant, chain

    def measure(s: dict[str, Any], knobs: dict[str, Any], prep: tuple[Any, Any]) -> dict[str, float]:
        variant, chain = prep
        effects = knobs["effects"]
        secs, diffs = [], []
        for k in s["ids"]:
            best = np.inf  # min of two: load on a shared machine only ever adds time
            for _ in range(2):
                t0 = time.perf_counter()
                _, rgb, _, _ = render_frame(variant, chain, k, s["renderer"], s["caster"])
                best = min(best, time.perf_counter() - t0)
            secs.append(best)
            diffs.append(float(np.mean(np.abs(np.clip(rgb, 0, 1) - s["ref"][k]))))  # linear RGB in [0, 1]
        return {"ms_per_frame": 1000 * float(np.median(secs)), "fidelity": 1.0 - float(np.mean(diffs)),
                "effects": float(len(effects))}

    w, h = data.size.clip_resolution
    return Sweep(
        "sim", tuple(SweepPoint(n, {"effects": list(e)}) for n, e in SIM_VARIANTS.items()),
        Metric("fidelity", "fidelity to the all-effects image (1 - mean |diff|)", True),
        Metric("ms_per_frame", "ms per frame (render + ground truth + effects)"), measure, setup, prepare=prepare,
        description=(f"Simulator cost with subsets of the water effects switched on, default scene at {w}x{h}, "
                     f"{n_frames} frames (per frame the faster of two renders, then the median). Fidelity = 1 - mean "
                     "absolute RGB difference (0..1) to the image with "
                     "every effect: what dropping effects costs in realism."),
        teardown=lambda s: s["renderer"].close())

"""The SfM sweep: presets and one-knob variants on the size's SfM clip, scored against the simulator's exact
cameras (:mod:`cadalign.evaluate.sfm`).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from cadalign.bench.data import BenchData
from cadalign.bench.framework import BenchConfig, Metric, Sweep, SweepPoint
from cadalign.config import resolve
from cadalign.evaluate.sfm import evaluate
from cadalign.io import fingerprint
from cadalign.sfm import PRESETS, SfMConfig, run

_NO_REFINE = ("balanced, no refinement", {"mapper": {"refine_iterations": 0}})


_GLOBAL = ("balanced, global mapper", {"mapper": {"kind": "global"}})


SFM_POINTS = {
    0: (("fast", {}), ("balanced", {}), ("accurate", {})),
    1: (("fast", {}), ("balanced", {}), ("accurate", {}), _NO_REFINE, _GLOBAL),
    2: (("fast", {}), ("balanced", {}), ("accurate", {}), _NO_REFINE, _GLOBAL,
        ("balanced, exhaustive", {"matching": {"pairing": "exhaustive"}})),
}
"""Presets and one-knob variants (features: the presets' SIFT budgets; matcher: pairing; mapper: kind and
refinement)."""


def _preset_of(name: str) -> str:
    return name.split(",")[0]


def sfm_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """SfM presets and feature/matcher/mapper variants: rotation error vs seconds, on the simulated SfM clip."""

    def measure(sim: Path, knobs: dict[str, Any], _: Any) -> dict[str, float]:
        c = resolve(SfMConfig, PRESETS, knobs["preset"], overrides={**knobs["overrides"], "num_threads": 1,
                                                                     "seed": cfg.seed})
        out = data.work("sfm", fingerprint(knobs))
        t0 = time.perf_counter()
        run(c, sim / "frames", out, overwrite=True)
        sec = time.perf_counter() - t0
        g = evaluate(out, sim)
        return {"sfm_s": sec, "rot_err_deg": g["rot_err_deg_mean"], "centre_rmse_m": g["centre_rmse_m"],
                "centre_rmse_rel": g["centre_rmse_rel"], "registration_rate": g["registration_rate"],
                "rel_rot_err_deg": g["rel_rot_err_deg_mean"]}

    w, h = data.size.sfm_resolution
    pts = tuple(SweepPoint(n, {"preset": _preset_of(n), "overrides": o}) for n, o in SFM_POINTS[data.size.level])
    return Sweep(
        "sfm", pts, Metric("rel_rot_err_deg", "relative rotation error of consecutive frames, mean (deg)"),
        Metric("sfm_s", "seconds per SfM run (1 thread)"), measure, data.sfm_clip,
        description=(f"SfM (pycolmap, 1 thread) on {data.size.sfm_frames} simulated frames at {w}x{h} of the default "
                     "scene, presets and single-knob variants, against the simulator's exact cameras. Accuracy: "
                     "the gauge-free rotation error between consecutive frames (the absolute rotation error after "
                     "a Sim(3) fit of the centres, rot_err_deg, is in the record: on a short arc the fit cannot pin "
                     "the roll about the path and that error mostly measures the gauge), with centre RMSE and "
                     "registration rate."),
        repeats=1 if data.size.level < 2 else 2)  # 1 thread + fixed seed: repeats only re-measure the time

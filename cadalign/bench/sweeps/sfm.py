"""The SfM sweep: plain pycolmap (the baseline), presets and one-knob variants on the size's SfM clip, scored
against the simulator's exact cameras (:mod:`cadalign.evaluate.sfm`).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.bench.data import BenchData
from cadalign.bench.framework import BenchConfig, Metric, Sweep, SweepPoint
from cadalign.config import resolve
from cadalign.errors import DegenerateGeometryError
from cadalign.evaluate.sfm import GT_SCENE, evaluate, pose_errors
from cadalign.io import fingerprint, read_json
from cadalign.sfm import PRESETS, SfMConfig, run
from cadalign.sfm.plain import run_plain
from cadalign.sfm.report import cameras_json

_NO_REFINE = ("balanced, no refinement", {"mapper": {"refine_iterations": 0}})


_GLOBAL = ("balanced, global mapper", {"mapper": {"kind": "global"}})


SFM_PLAIN = "plain pycolmap"
"""Name of the sfm sweep's baseline setting: pycolmap's SIFT, sequential matching and incremental mapping with its
defaults (:mod:`cadalign.sfm.plain`), on the same frames in the same run."""


SFM_POINTS = {
    0: ((SFM_PLAIN, {}), ("fast", {}), ("balanced", {}), ("accurate", {})),
    1: ((SFM_PLAIN, {}), ("fast", {}), ("balanced", {}), ("accurate", {}), _NO_REFINE, _GLOBAL),
    2: ((SFM_PLAIN, {}), ("fast", {}), ("balanced", {}), ("accurate", {}), _NO_REFINE, _GLOBAL,
        ("balanced, exhaustive", {"matching": {"pairing": "exhaustive"}})),
}
"""Plain pycolmap (the baseline), presets and one-knob variants (features: the presets' SIFT budgets; matcher:
pairing; mapper: kind and refinement)."""


def _preset_of(name: str) -> str:
    return name.split(",")[0]


def sfm_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """SfM presets and feature/matcher/mapper variants: rotation error vs seconds, on the simulated SfM clip."""

    def measure(sim: Path, knobs: dict[str, Any], _: Any) -> dict[str, float]:
        if knobs["preset"] == SFM_PLAIN:
            return plain_measure(sim, data.work("sfm", fingerprint(knobs)), cfg.seed)
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
        Metric("sfm_s", "seconds per SfM run (1 thread)"), measure, data.sfm_clip, baseline=SFM_PLAIN,
        description=(f"SfM (pycolmap, 1 thread) on {data.size.sfm_frames} simulated frames at {w}x{h} of the default "
                     f"scene, presets and single-knob variants, against the simulator's exact cameras; '{SFM_PLAIN}' "
                     "(SIFT, sequential matching, incremental mapping, pycolmap's defaults, one shared camera) runs "
                     "on the same frames in the same run, and the cost ratio divides each setting's seconds by its "
                     "seconds. Accuracy: "
                     "the gauge-free rotation error between consecutive frames (the absolute rotation error after "
                     "a Sim(3) fit of the centres, rot_err_deg, is in the record: on a short arc the fit cannot pin "
                     "the roll about the path and that error mostly measures the gauge), with centre RMSE and "
                     "registration rate."),
        repeats=1 if data.size.level < 2 else 2)  # 1 thread + fixed seed: repeats only re-measure the time


def plain_measure(sim: Path, work: Path, seed: int) -> dict[str, float]:
    """Plain pycolmap (:func:`cadalign.sfm.plain.run_plain`, 1 thread) on ``sim``'s frames, scored like the presets.

    Raises:
        DegenerateGeometryError: plain pycolmap found no model (the setting is then recorded as failed).
    """
    res = run_plain(sim / "frames", work, num_threads=1, seed=seed)
    if res.model is None:
        raise DegenerateGeometryError(f"plain pycolmap found no model in {res.frames} frames")
    gt = read_json(sim / GT_SCENE / "cameras.json")
    pe = pose_errors(cameras_json(res.model), gt)
    rmse = float(np.sqrt(np.mean(pe.centre_err_m**2)))
    return {"sfm_s": res.seconds["total"], "rot_err_deg": float(pe.rot_err_deg.mean()), "centre_rmse_m": rmse,
            "registration_rate": len(pe.names) / len(gt["frames"]),
            "rel_rot_err_deg": float(pe.rel_rot_err_deg.mean()),
            **{f"{k}_s": v for k, v in res.seconds.items() if k != "total"}}

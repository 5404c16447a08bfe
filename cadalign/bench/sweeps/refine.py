"""The pose refinement sweep (:func:`cadalign.bench.refine.refine_sweep`) on the size's SfM clip.
"""
from __future__ import annotations

from typing import Any

from cadalign.bench.data import BenchData
from cadalign.bench.framework import BenchConfig, Metric, Sweep, SweepPoint
from cadalign.bench.refine import refine_sweep as sweep
from cadalign.bench.sweeps.train import SCENE
from cadalign.infer.config import RefineConfig
from cadalign.sim.structure import load_structure

REFINE_ITERS = {0: (0, 1, 3), 1: (0, 1, 2, 5, 10), 2: (0, 1, 2, 3, 5, 10, 20)}


def refine_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """Silhouette + depth refinement iterations from oracle-noisy poses: ADD vs ms per instance."""
    max_frames = (4, 8, 16)[data.size.level]

    def setup() -> dict[str, Any]:
        return {"scene": data.sfm_clip() / SCENE, "models": load_structure(data.scene()).models}

    def measure(s: dict[str, Any], knobs: dict[str, Any], _: Any) -> dict[str, float]:
        rows = sweep(s["scene"], s["models"], iters=(knobs["iters"],), cfg=RefineConfig(seed=cfg.seed),
                     max_frames=max_frames)
        r = next(r for r in rows if r.method == knobs["method"])
        return {"add_m": r.add_m, "r_err_deg": r.r_err_deg, "t_err_m": r.t_err_m, "ms_per_instance": r.ms,
                "instances": float(r.n), "eligible": float(r.n_eligible), "mean_iters": r.mean_iters}

    return Sweep(
        "refine", tuple(SweepPoint(f"{n} it", {"iters": n, "method": "both"}) for n in REFINE_ITERS[data.size.level]),
        Metric("add_m", "ADD pose error, mean (m)"), Metric("ms_per_instance", "ms per instance"), measure, setup,
        description=(f"Pose refinement (silhouette then depth ICP) of valves and hot stabs from the oracle "
                     f"detector's noisy poses with true masks, first {max_frames} frames of the SfM clip (the default "
                     "refinement skips masks under 400 px, so the small clip would refine nothing); ADD over all "
                     "instances, refined or not. The iteration budget is the knob (infer.bench.refine_sweep; it "
                     "averages over instances, so one repeat)."),
        repeats=1)

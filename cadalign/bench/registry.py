"""``cadalign bench STAGE|all --out DIR``: every stage's sweep by name (:func:`make_sweep`) and the run over stages
(:func:`run_bench`). The framework (settings, timing, storage, Pareto front) is :mod:`cadalign.bench.framework`,
re-exported here; the sweeps (:mod:`cadalign.bench.sweeps`, one module per stage) import the framework, not this
registry.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from cadalign.bench.data import BenchData, size_spec
from cadalign.bench.framework import (
    BENCH_JSON,
    FORMAT,
    STAGES,
    BenchConfig,
    BenchStore,
    Metric,
    Progress,
    Sweep,
    SweepPoint,
    current_records,
    json_safe,
    knob_note,
    load_bench,
    measure_point,
    num,
    peak_memory,
    point_key,
    replot_stage,
    run_sweep,
    stage_rows,
    summarise_stage,
)
from cadalign.bench.report import write_bench_report
from cadalign.bench.sweeps import align, emulate, fuse, infer, refine, render, sfm, sim, train
from cadalign.errors import ConfigError

__all__ = [
    "BENCH_JSON", "BenchConfig", "BenchStore", "FORMAT", "Metric", "STAGES", "Sweep", "SweepPoint",
    "current_records", "json_safe", "knob_note", "load_bench", "measure_point", "num", "Progress", "peak_memory",
    "point_key", "replot_stage", "run_sweep", "stage_rows", "summarise_stage", "make_sweep", "run_bench",
]


def make_sweep(stage: str, data: Any, cfg: BenchConfig) -> Sweep:
    """The :class:`Sweep` of ``stage`` on ``data`` (a :class:`~cadalign.bench.data.BenchData`)."""
    makers = {"infer": infer.infer_sweep, "sim": sim.sim_sweep, "render": render.render_sweep,
              "align": align.align_sweep, "fuse": fuse.fuse_sweep, "emulate": emulate.emulate_sweep,
              "sfm": sfm.sfm_sweep, "seg": train.seg_sweep, "depth": train.depth_sweep, "refine": refine.refine_sweep}
    if stage not in makers:
        raise ConfigError(f"unknown bench stage {stage!r}; allowed: {', '.join(STAGES)} or all")
    return makers[stage](data, cfg)


def run_bench(stages: Iterable[str], out_dir: Path, cfg: BenchConfig, *, overwrite: bool = False,
              progress: Progress | None = None, report: bool = True,
              sweeps: dict[str, Callable[[Any, BenchConfig], Sweep]] | None = None) -> dict[str, Any]:
    """Sweep ``stages`` into ``out_dir`` (bench.json, pareto_<stage>.png, bench.html); returns bench.json's dict.

    ``sweeps`` maps a stage to its own ``(data, cfg) -> Sweep`` maker instead of :func:`make_sweep` (e.g. the
    infer sweep on a user's network)."""
    out_dir = Path(out_dir)
    store = BenchStore(out_dir, cfg, overwrite=overwrite)
    data = BenchData(out_dir / "data", size_spec(cfg.size), cfg.seed)
    for stage in stages:
        maker = (sweeps or {}).get(stage)
        run_sweep(maker(data, cfg) if maker else make_sweep(stage, data, cfg), store, progress=progress)
    if report:
        write_bench_report(out_dir)
    return store.data

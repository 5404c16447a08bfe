"""The accuracy-versus-time benchmark framework behind ``cadalign bench STAGE|all --out DIR``.

A :class:`Sweep` is one stage's list of settings (:class:`SweepPoint`: a name and a knobs dict), how to
build what every setting shares (``setup``, not timed: a simulated clip, a mesh), what a setting needs
before it is timed (``prepare``, not timed: e.g. training a small network) and the timed call
(``measure``) that returns the metrics of one run. :func:`run_sweep` runs each setting ``repeats``
times and records per setting:

* every metric (median over the repeats) and the named accuracy metric;
* ``seconds``: the wall time of ``measure`` (median over the repeats, every repeat kept in
  ``seconds_all``); the stage's *cost* is either these seconds or one of its own metrics (ms per frame,
  seconds per frame) when the stage says so (``Sweep.cost.key``);
* ``peak_rss_mb``: the largest resident set size of the process (``VmRSS`` of ``/proc/self/status``,
  read every 5 ms by a background thread, Linux; elsewhere ``resource.getrusage`` ``ru_maxrss``, a
  lifetime maximum) while the setting's ``measure`` calls ran, and ``peak_rss_delta_mb`` above the RSS
  when they started (what the setting itself allocated, within the sampling period).

Everything goes to ``DIR/bench.json`` after each setting (atomic write), so an interrupted run continues
where it stopped, and a finished setting (same stage, name, knobs, size and repeats) is reused on re-run.
A benchmark folder made with another size/repeats/seed is refused unless ``overwrite``.
"""

from __future__ import annotations

import logging
import math
import os
import platform
import resource
import statistics
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cadalign._version import __version__
from cadalign.bench.pareto import TOLERANCE, pareto_front, plot_pareto, recommend
from cadalign.errors import ConfigError
from cadalign.io import fingerprint, read_json, write_json
from cadalign.types import Progress

log = logging.getLogger(__name__)

BENCH_JSON = "bench.json"
FORMAT = "cadalign-bench/1"


@dataclass(frozen=True)
class Metric:
    """Which value of a setting's record is plotted on an axis, and how it reads."""

    key: str
    """Metric name in the record's ``metrics`` (or ``seconds`` for the wall time of ``measure``)."""
    label: str
    """Axis label with the unit."""
    higher_is_better: bool = False
    """Direction: accuracy metrics such as IoU are higher-is-better, errors and costs lower-is-better."""


@dataclass(frozen=True)
class SweepPoint:
    """One setting of a stage."""

    name: str
    """Short name shown in plots and tables."""
    knobs: dict[str, Any] = field(default_factory=dict)
    """The knob values (JSON-serialisable); passed to ``prepare`` and ``measure``."""


@dataclass(frozen=True)
class Sweep:
    """One stage's settings and how to run them (see the module doc)."""

    stage: str
    """Stage name (the CLI subcommand)."""
    points: tuple[SweepPoint, ...]
    """The settings, at least three."""
    accuracy: Metric
    """The accuracy axis."""
    cost: Metric
    """The cost axis (lower is better); ``key = 'seconds'`` is the measured wall time."""
    measure: Callable[[Any, dict[str, Any], Any], dict[str, float]]
    """``(shared, knobs, prepared) -> metrics``; timed, run ``repeats`` times."""
    setup: Callable[[], Any] = lambda: None
    """Builds the shared state once, only when some setting still has to run (not timed)."""
    prepare: Callable[[Any, dict[str, Any]], Any] | None = None
    """``(shared, knobs) -> prepared``, once per setting before its repeats (not timed)."""
    description: str = ""
    """One paragraph for the report: what is swept, on which data, what the axes mean."""
    teardown: Callable[[Any], None] | None = None
    """Releases the shared state (e.g. closes a GL context) after the sweep."""
    repeats: int | None = None
    """Repeats for this stage (default: the run's); 1 for stages whose single run already repeats inside."""
    baseline: str | None = None
    """Name of the setting the others' costs are divided by (``cost_ratio`` in each record), measured in the same
    run; None: no ratio."""


@dataclass(frozen=True)
class BenchConfig:
    """What a benchmark folder was made with (a folder refuses another one unless overwritten)."""

    size: str = "small"
    """tiny (tests: seconds per stage), small (minutes), full (what a person runs, up to ~1 h on 2 cores)."""
    repeats: int = 3
    """Timed runs per setting; medians are reported."""
    seed: int = 0
    """Seed of every random choice in the sweeps."""


def point_key(stage: str, point: SweepPoint, cfg: BenchConfig, repeats: int) -> str:
    """Fingerprint of a setting's record: reused on re-run only when all of these match."""
    return fingerprint({"stage": stage, "name": point.name, "knobs": point.knobs, "size": cfg.size,
                        "repeats": repeats, "seed": cfg.seed})


def _rss_mb() -> float | None:
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


@contextmanager
def peak_memory(period_s: float = 0.005) -> Iterator[dict[str, float]]:
    """Sample the process RSS in a background thread; on exit the dict holds ``peak_rss_mb``,
    ``start_rss_mb`` and ``method``. Falls back to ``ru_maxrss`` (lifetime peak) without /proc."""
    out: dict[str, Any] = {}
    start = _rss_mb()
    if start is None:
        yield out
        out.update(peak_rss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
                   start_rss_mb=float("nan"), method="getrusage ru_maxrss (lifetime peak)")
        return
    peak = [start]
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(period_s):
            v = _rss_mb()
            if v is not None and v > peak[0]:
                peak[0] = v

    th = threading.Thread(target=sample, name="bench-rss", daemon=True)
    th.start()
    try:
        yield out
    finally:
        stop.set()
        th.join()
        end = _rss_mb()
        out.update(peak_rss_mb=max(peak[0], end or 0.0), start_rss_mb=start,
                   method=f"/proc/self/status VmRSS sampled every {1000 * period_s:g} ms")


def _median_metrics(runs: list[dict[str, float]]) -> dict[str, float]:
    keys = {k for r in runs for k in r}
    out = {}
    for k in sorted(keys):
        vals = [float(r[k]) for r in runs if k in r and r[k] is not None]
        finite = [v for v in vals if math.isfinite(v)]
        out[k] = statistics.median(finite) if finite else float("nan")
    return out


def measure_point(sweep: Sweep, shared: Any, point: SweepPoint, repeats: int) -> dict[str, Any]:
    """Prepare and run one setting ``repeats`` times; the record written to bench.json."""
    t0 = time.perf_counter()
    prepared = sweep.prepare(shared, point.knobs) if sweep.prepare else None
    prepare_s = time.perf_counter() - t0
    runs, seconds = [], []
    with peak_memory() as mem:
        for _ in range(repeats):
            t = time.perf_counter()
            runs.append(sweep.measure(shared, point.knobs, prepared))
            seconds.append(time.perf_counter() - t)
    metrics = _median_metrics(runs)
    rec = {"name": point.name, "knobs": point.knobs, "status": "done", "metrics": metrics,
           "seconds": statistics.median(seconds), "seconds_min": min(seconds), "seconds_all": seconds,
           "prepare_seconds": prepare_s,
           "peak_rss_mb": mem["peak_rss_mb"], "peak_rss_delta_mb": mem["peak_rss_mb"] - mem["start_rss_mb"],
           "memory_method": mem["method"], "repeats": repeats}
    rec["accuracy"] = _axis_value(rec, sweep.accuracy)
    rec["cost"] = _axis_value(rec, sweep.cost)
    return rec


def _axis_value(rec: dict[str, Any], m: Metric) -> float:
    return num(rec["seconds"] if m.key == "seconds" else rec["metrics"].get(m.key))


class BenchStore:
    """``DIR/bench.json``: the config, and per stage its axes and the record of every setting."""

    def __init__(self, out_dir: Path, cfg: BenchConfig, *, overwrite: bool = False) -> None:
        self.out_dir = Path(out_dir)
        self.path = self.out_dir / BENCH_JSON
        self.cfg = cfg
        config = {"size": cfg.size, "repeats": cfg.repeats, "seed": cfg.seed}
        if self.path.is_file() and not overwrite:
            self.data = read_json(self.path)
            if self.data.get("config") != config:
                raise ConfigError(f"{self.path} was made with {self.data.get('config')}, not {config}; choose "
                                  "another --out folder or pass --overwrite")
        else:
            self.data = {"format": FORMAT, "version": __version__, "config": config, "stages": {},
                         "machine": {"cpu_count": os.cpu_count(), "processor": platform.processor()
                                     or platform.machine(), "python": platform.python_version()}}

    def stage(self, sweep: Sweep) -> dict[str, Any]:
        st = self.data["stages"].setdefault(sweep.stage, {"points": {}})
        st.update(description=sweep.description, accuracy=sweep.accuracy.__dict__, cost=sweep.cost.__dict__,
                  order=[p.name for p in sweep.points], baseline=sweep.baseline)
        return st

    def save(self) -> Path:
        self.data["load_avg_1min"] = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
        return write_json(self.path, json_safe(self.data))


def json_safe(obj: Any) -> Any:
    """``obj`` with non-finite floats replaced by None (bench.json stays strict JSON)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def num(v: Any) -> float:
    """A record value as a float (None, i.e. a non-finite value in bench.json, is NaN)."""
    return float("nan") if v is None else float(v)


def run_sweep(sweep: Sweep, store: BenchStore, *, progress: Progress | None = None) -> dict[str, Any]:
    """Run every unfinished setting of ``sweep`` (saving after each), then the summary and the Pareto plot.

    A setting that raises is recorded as ``failed`` with the error (and reused as such); a
    KeyboardInterrupt leaves the finished settings on disk. Returns the stage's bench.json section.
    """
    if len(sweep.points) < 3:
        raise ConfigError(f"stage '{sweep.stage}' has {len(sweep.points)} settings; a sweep needs at least 3")
    repeats = sweep.repeats or store.cfg.repeats
    st = store.stage(sweep)
    keyed = [(point_key(sweep.stage, p, store.cfg, repeats), p) for p in sweep.points]
    todo = [(k, p) for k, p in keyed if k not in st["points"]]
    if todo:
        log.info("bench %s: %d of %d settings to run", sweep.stage, len(todo), len(keyed))
        shared = sweep.setup()
        items = progress(todo, f"bench {sweep.stage}", len(todo)) if progress else todo
        try:
            for key, p in items:
                try:
                    rec = measure_point(sweep, shared, p, repeats)
                except Exception as exc:  # a failing setting (e.g. SfM registers nothing) is a result too
                    log.warning("bench %s: setting '%s' failed: %s", sweep.stage, p.name, exc)
                    rec = {"name": p.name, "knobs": p.knobs, "status": "failed",
                           "error": f"{type(exc).__name__}: {exc}"[:2000], "traceback": traceback.format_exc(limit=6),
                           "accuracy": float("nan"), "cost": float("nan")}
                st["points"][key] = rec
                store.save()
        finally:
            if sweep.teardown is not None:
                sweep.teardown(shared)
    summarise_stage(sweep.stage, st, [k for k, _ in keyed], store.out_dir)
    store.save()
    return st


def current_records(st: dict[str, Any], keys: list[str]) -> list[dict[str, Any]]:
    """The records of ``keys`` in sweep order (older records of other settings stay in the file)."""
    return [st["points"][k] for k in keys if k in st["points"]]


def summarise_stage(stage: str, st: dict[str, Any], keys: list[str], out_dir: Path) -> None:
    """Add ``current``, ``pareto``, ``recommended`` and ``plot`` to a stage section and draw its plot."""
    recs = current_records(st, keys)
    acc = st["accuracy"]
    costs = [num(r["cost"]) for r in recs]
    accs = [num(r["accuracy"]) for r in recs]
    front = pareto_front(costs, accs, higher_is_better=acc["higher_is_better"])
    rec = recommend(costs, accs, higher_is_better=acc["higher_is_better"])
    base = [r for r in recs if r["name"] == st.get("baseline") and r["status"] == "done"]
    for r in recs:  # every setting's cost over the baseline's, both from this run's records
        r["cost_ratio"] = num(r["cost"]) / num(base[0]["cost"]) if base and num(base[0]["cost"]) > 0 else None
    st["current"] = keys
    st["pareto"] = [recs[i]["name"] for i in front]
    st["recommended"] = recs[rec]["name"] if rec is not None else None
    st["tolerance"] = TOLERANCE
    st["plot"] = f"pareto_{stage}.png"
    replot_stage({"stages": {stage: st}}, stage, out_dir / st["plot"])


def replot_stage(bench: dict[str, Any], stage: str, path: Path) -> Path:
    """Draw the Pareto plot of ``stage`` from a bench.json dict into ``path`` (what the notebook calls)."""
    st = bench["stages"][stage]
    recs = current_records(st, st.get("current", list(st["points"])))
    acc, cost = st["accuracy"], st["cost"]
    return plot_pareto(path, [r["name"] for r in recs], [num(r["cost"]) for r in recs],
                       [num(r["accuracy"]) for r in recs], higher_is_better=acc["higher_is_better"],
                       cost_label=cost["label"], acc_label=acc["label"],
                       title=f"{stage}: recommended '{st.get('recommended')}'",
                       notes=[knob_note(r["knobs"]) for r in recs])


def knob_note(knobs: dict[str, Any], max_len: int = 48) -> str:
    """Compact ``k=v`` text of a knobs dict for plot annotations; nested dicts flatten to ``a.b=v``.

    >>> knob_note({"preset": "fast", "overrides": {"mapper": {"kind": "global"}}, "extra": {}})
    'preset=fast overrides.mapper.kind=global'
    """
    def flat(d: dict[str, Any], prefix: str = "") -> list[str]:
        out = []
        for k, v in d.items():
            out += flat(v, f"{prefix}{k}.") if isinstance(v, dict) else [f"{prefix}{k}={v}"]
        return out

    text = " ".join(flat(knobs))
    return text if len(text) <= max_len else text[: max_len - 1] + "…"


def load_bench(out_dir: Path) -> dict[str, Any]:
    """``DIR/bench.json`` (or the file itself) as a dict."""
    p = Path(out_dir)
    return read_json(p if p.suffix == ".json" else p / BENCH_JSON)


def stage_rows(bench: dict[str, Any], stage: str) -> list[dict[str, Any]]:
    """The current settings of ``stage`` in sweep order, as flat rows (name, knobs, accuracy, cost …)."""
    st = bench["stages"][stage]
    rows = []
    for r in current_records(st, st.get("current", list(st["points"]))):
        rows.append({"setting": r["name"], "knobs": knob_note(r["knobs"], 80), "status": r["status"],
                     st["accuracy"]["label"]: num(r["accuracy"]), st["cost"]["label"]: num(r["cost"]),
                     **({f"cost / {st['baseline']}": num(r.get("cost_ratio"))} if st.get("baseline") else {}),
                     "wall s (median)": num(r.get("seconds")), "peak RSS MB": num(r.get("peak_rss_mb")),
                     "Pareto": r["name"] in st.get("pareto", []),
                     "recommended": r["name"] == st.get("recommended")})
    return rows


STAGES = ("sim", "sfm", "align", "render", "seg", "depth", "refine", "infer", "fuse", "emulate")
"""Every benchmarked stage, in the order ``bench all`` runs them."""

"""The sweep framework: records, medians, resume, failures, config refusal, strict JSON, peak memory."""

from __future__ import annotations

import json

import numpy as np
import pytest

from cadalign.bench.registry import (
    BenchConfig,
    BenchStore,
    Metric,
    Sweep,
    SweepPoint,
    load_bench,
    peak_memory,
    run_sweep,
    stage_rows,
)
from cadalign.errors import ConfigError


def toy_sweep(calls: list[str], *, fail: str | None = None, interrupt: str | None = None) -> Sweep:
    """Accuracy = 1 - 1/(n+1), cost = n (reported as a metric), for n in 1, 2, 4, 8."""

    def measure(shared, knobs, prepared):
        calls.append(knobs["n"])
        if knobs["n"] == fail:
            raise RuntimeError("boom")
        if knobs["n"] == interrupt:
            raise KeyboardInterrupt
        n = knobs["n"]
        return {"acc": 1 - 1 / (n + 1) + shared + prepared, "cost_ms": float(n), "undefined": float("nan")}

    pts = tuple(SweepPoint(f"n{n}", {"n": n}) for n in (1, 2, 4, 8))
    return Sweep("toy", pts, Metric("acc", "accuracy", True), Metric("cost_ms", "ms"), measure,
                 setup=lambda: 0.0, prepare=lambda s, k: 0.0, description="toy")


def test_records_medians_front_and_recommendation(tmp_path):
    calls: list = []
    store = BenchStore(tmp_path, BenchConfig("tiny", 3, 0))
    st = run_sweep(toy_sweep(calls), store)
    assert calls == [1, 1, 1, 2, 2, 2, 4, 4, 4, 8, 8, 8]
    recs = [st["points"][k] for k in st["current"]]
    assert [r["accuracy"] for r in recs] == pytest.approx([0.5, 2 / 3, 0.8, 8 / 9])
    assert [r["cost"] for r in recs] == [1.0, 2.0, 4.0, 8.0]
    assert all(len(r["seconds_all"]) == 3 and r["peak_rss_mb"] > 0 for r in recs)
    # best 0.889, threshold 0.844: only n8 qualifies
    assert st["recommended"] == "n8" and st["pareto"] == ["n1", "n2", "n4", "n8"]
    assert (tmp_path / "pareto_toy.png").is_file()
    # strict JSON: NaN became null
    text = (tmp_path / "bench.json").read_text()
    json.loads(text, parse_constant=lambda c: pytest.fail(f"non-strict JSON constant {c}"))
    rows = stage_rows(load_bench(tmp_path), "toy")
    assert [r["setting"] for r in rows] == ["n1", "n2", "n4", "n8"] and rows[3]["recommended"]


def test_finished_points_are_reused_and_interrupted_runs_continue(tmp_path):
    calls: list = []
    cfg = BenchConfig("tiny", 1, 0)
    with pytest.raises(KeyboardInterrupt):
        run_sweep(toy_sweep(calls, interrupt=4), BenchStore(tmp_path, cfg))
    assert calls == [1, 2, 4]
    saved = load_bench(tmp_path)["stages"]["toy"]["points"]
    assert sorted(r["name"] for r in saved.values()) == ["n1", "n2"]
    calls.clear()
    run_sweep(toy_sweep(calls), BenchStore(tmp_path, cfg))
    assert calls == [4, 8]  # n1, n2 reused
    calls.clear()
    st = run_sweep(toy_sweep(calls), BenchStore(tmp_path, cfg))
    assert calls == [] and st["recommended"] == "n8"


def test_failed_setting_is_recorded_and_not_chosen(tmp_path):
    calls: list = []
    st = run_sweep(toy_sweep(calls, fail=8), BenchStore(tmp_path, BenchConfig("tiny", 1, 0)))
    failed = [r for r in st["points"].values() if r["status"] == "failed"]
    assert [r["name"] for r in failed] == ["n8"] and "RuntimeError: boom" in failed[0]["error"]
    assert st["recommended"] == "n4"  # best of the finished ones (0.8), nothing else within 5%


def test_other_config_is_refused_unless_overwrite(tmp_path):
    run_sweep(toy_sweep([]), BenchStore(tmp_path, BenchConfig("tiny", 1, 0)))
    with pytest.raises(ConfigError, match="--overwrite"):
        BenchStore(tmp_path, BenchConfig("tiny", 2, 0))
    store = BenchStore(tmp_path, BenchConfig("tiny", 2, 0), overwrite=True)
    assert store.data["stages"] == {}


def test_sweep_needs_three_settings(tmp_path):
    sw = toy_sweep([])
    small = Sweep("toy", sw.points[:2], sw.accuracy, sw.cost, sw.measure)
    with pytest.raises(ConfigError, match="at least 3"):
        run_sweep(small, BenchStore(tmp_path, BenchConfig("tiny", 1, 0)))


def test_peak_memory_sees_an_allocation():
    with peak_memory(period_s=0.001) as mem:
        a = np.ones(20_000_000)  # 160 MB, touched
        a[::4096] += 1.0
        del a
    assert mem["peak_rss_mb"] - mem["start_rss_mb"] > 80
    assert "VmRSS" in mem["method"]


def test_costs_are_divided_by_the_baseline_of_the_same_run(tmp_path):
    calls: list = []
    sweep = toy_sweep(calls)
    st = run_sweep(Sweep(**{**sweep.__dict__, "baseline": "n2"}), BenchStore(tmp_path, BenchConfig("tiny", 1, 0)))
    recs = [st["points"][k] for k in st["current"]]
    assert [r["cost_ratio"] for r in recs] == pytest.approx([0.5, 1.0, 2.0, 4.0])
    rows = stage_rows(load_bench(tmp_path), "toy")
    assert [r["cost / n2"] for r in rows] == pytest.approx([0.5, 1.0, 2.0, 4.0])
    # a failed baseline leaves no ratio rather than a wrong one
    st = run_sweep(Sweep(**{**toy_sweep([], fail=2).__dict__, "baseline": "n2"}),
                   BenchStore(tmp_path / "failed", BenchConfig("tiny", 1, 0)))
    assert all(st["points"][k]["cost_ratio"] is None for k in st["current"])
    # no baseline: no ratio column
    run_sweep(toy_sweep([]), BenchStore(tmp_path / "plain", BenchConfig("tiny", 1, 0)))
    assert not any(k.startswith("cost /") for k in stage_rows(load_bench(tmp_path / "plain"), "toy")[0])

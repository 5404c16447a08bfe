"""``DIR/bench.html``: one self-contained page (plots inlined as base64) of a benchmark folder.

Per stage: what was swept, the Pareto plot with, beside it, every setting's cost as a ratio of the stage's
baseline (run in the same process on the same data), the recommended setting (within 5 % of the best accuracy at
the least time) and a table of every setting; then the low-visibility robustness section when
``robustness.json`` is there.
"""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

from cadalign.bench.framework import BENCH_JSON, STAGES, load_bench, num, stage_rows
from cadalign.formats.html import CSS, img_tag, table
from cadalign.io import read_json, write_text

BENCH_HTML = "bench.html"


def recommendations(bench: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per stage: the recommended setting with its accuracy and cost (the page's summary table)."""
    rows = []
    for stage in _stage_order(bench):
        st = bench["stages"][stage]
        by_name = {r["setting"]: r for r in stage_rows(bench, stage)}
        rec = st.get("recommended")
        r = by_name.get(rec, {})
        rows.append({"stage": stage, "recommended setting": rec or "(none finished)",
                     "accuracy": r.get(st["accuracy"]["label"], float("nan")),
                     "accuracy metric": st["accuracy"]["label"],
                     "cost": r.get(st["cost"]["label"], float("nan")), "cost metric": st["cost"]["label"],
                     "settings": len(by_name), "failed": sum(v["status"] != "done" for v in by_name.values())})
    return rows


def _stage_order(bench: dict[str, Any]) -> list[str]:
    known = [s for s in STAGES if s in bench["stages"]]
    return known + sorted(s for s in bench["stages"] if s not in known)


RATIO_KEYS = {"fps_vs_open3d": "Open3D VBG alone frames/s / setting's (interleaved)",
              "cost_vs_open3d": "setting's s / Open3D alone on its rays"}
"""Per-record ratios some sweeps time against their baseline inside each measurement (column titles)."""


def baseline_rows(bench: dict[str, Any], stage: str) -> list[dict[str, Any]]:
    """Each current setting's cost as a ratio of the stage's baseline (and the in-measurement ratios of
    ``RATIO_KEYS`` when the records have them); empty when the stage has no baseline."""
    st = bench["stages"][stage]
    if not st.get("baseline"):
        return []
    recs = [st["points"][k] for k in st.get("current", list(st["points"])) if k in st["points"]]
    extra = [k for k in RATIO_KEYS if any(k in (r.get("metrics") or {}) for r in recs)]
    return [{"setting": r["name"], f"cost / {st['baseline']}": num(r.get("cost_ratio")),
             **{RATIO_KEYS[k]: num((r.get("metrics") or {}).get(k)) for k in extra}} for r in recs]


def _baseline_box(bench: dict[str, Any], stage: str) -> str:
    rows = baseline_rows(bench, stage)
    if not rows:
        return ""
    name = html.escape(str(bench["stages"][stage]["baseline"]))
    return (f"<div class='baseline'><p><b>Against the baseline</b> '{name}', measured in the same run on the same "
            f"data (a ratio, not an absolute time, is the result on a shared machine):</p>{table(rows)}</div>")


def _stage_section(out: Path, bench: dict[str, Any], stage: str) -> str:
    st = bench["stages"][stage]
    rec = st.get("recommended")
    failed = [r for r in st["points"].values() if r["status"] != "done" and r["name"] in st.get("order", [])]
    errs = "".join(f"<p class='pending'>{html.escape(r['name'])} failed: {html.escape(str(r.get('error')))}</p>"
                   for r in failed)
    return (f"<h2 id='{stage}'>{html.escape(stage)}</h2><p>{html.escape(st.get('description', ''))}</p>"
            f"<p><b>Recommended:</b> <span class='rec'>{html.escape(str(rec))}</span> (within "
            f"{100 * st.get('tolerance', 0.05):.0f}% of the best {html.escape(st['accuracy']['label'])}, least "
            f"{html.escape(st['cost']['label'])})</p>{errs}"
            + "<div class='plotrow'>" + img_tag(out / st.get("plot", f"pareto_{stage}.png"), f"Pareto plot {stage}")
            + _baseline_box(bench, stage) + "</div>"
            + table(stage_rows(bench, stage)))


def _robustness_section(out: Path, rob: dict[str, Any]) -> str:
    rows = [{"effect": r["effect"], "severity": r["severity"], "value": str(r["value"]),
             **{k: num(v) for k, v in r["metrics"].items()}, "note": r.get("note") or ""} for r in rob["rows"]]
    plots = "".join(img_tag(out / p, f"robustness {k}") for k, p in rob.get("plots", {}).items())
    return (f"<h2 id='robustness'>Robustness under low visibility</h2><p>{html.escape(rob.get('description', ''))}</p>"
            + plots + table(rows))


def write_bench_report(out_dir: Path) -> Path:
    """Write ``out_dir/bench.html`` from ``bench.json`` (and ``robustness.json`` if present); returns its path."""
    out = Path(out_dir)
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>cadalign bench</title><style>{CSS}"
             ".rec{color:#a00;font-weight:bold}.plotrow{display:flex;gap:1em;align-items:flex-start}"
             ".baseline{max-width:40em}</style></head><body><h1>cadalign accuracy-vs-time benchmark</h1>"]
    bench = load_bench(out) if (out / BENCH_JSON).is_file() else None
    if bench is not None:
        c = bench["config"]
        m = bench.get("machine", {})
        parts.append(f"<p>Size <b>{html.escape(str(c['size']))}</b>, {c['repeats']} repeats per setting (medians), "
                     f"seed {c['seed']}; {m.get('cpu_count')} CPUs ({html.escape(str(m.get('processor')))}), "
                     f"1-min load {num(bench.get('load_avg_1min')):.1f} at the last write. Peak memory: "
                     "process RSS sampled while the setting ran.</p>")
        parts.append("<h2 id='summary'>Recommended settings</h2>" + table(recommendations(bench)))
        parts += [_stage_section(out, bench, s) for s in _stage_order(bench)]
    if (out / "robustness.json").is_file():
        parts.append(_robustness_section(out, read_json(out / "robustness.json")))
    if bench is not None:
        parts.append("<h2 id='json'>bench.json config</h2><pre>" + html.escape(json.dumps(bench["config"], indent=1))
                     + "</pre>")
    parts.append("</body></html>")
    return write_text(out / BENCH_HTML, "\n".join(parts))

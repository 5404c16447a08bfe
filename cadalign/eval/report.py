"""A self-contained HTML report (images inlined as base64) of a demo or benchmark run."""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from typing import Any

from cadalign.io import write_text

CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1200px;color:#222}
h1{color:#034}h2{border-bottom:1px solid #ccc;padding-bottom:.2em}
table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#eef}td:first-child,th:first-child{text-align:left}img{max-width:100%;border:1px solid #ccc}
.pending{color:#a60}"""


def img_tag(path: Path, alt: str) -> str:
    """An <img> with the PNG inlined, or a note when the file is missing."""
    path = Path(path)
    if not path.is_file():
        return f"<p class='pending'>missing image: {html.escape(str(path.name))}</p>"
    data = base64.b64encode(path.read_bytes()).decode()
    return f"<img alt='{html.escape(alt)}' src='data:image/png;base64,{data}'>"


def table(rows: list[dict[str, Any]]) -> str:
    if not rows:
        return "<p>(no rows)</p>"
    cols = list(rows[0])
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in cols)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(_fmt(r.get(c)))}</td>" for c in cols) + "</tr>" for r in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _sim_section(out: Path, info: dict) -> str:
    rep = info["report"]
    rows = [
        {"step": k, "ms per frame (median)": 1000 * v} for k, v in rep["seconds_per_frame_median"].items()
    ]
    return (
        f"<h2 id='sim'>Simulation</h2><p>Scene <b>{html.escape(rep['scene'])}</b>, {rep['frames']} frames at "
        f"{rep['resolution'][0]}×{rep['resolution'][1]}, effects: {html.escape(', '.join(rep['effects']) or 'none')}."
        f"</p>{table(rows)}<h3>Contact sheet: clean render, each effect alone, all effects</h3>"
        + img_tag(out / info["dir"] / "contact_sheet.png", "contact sheet")
    )


def write_report(out: Path, summary: dict) -> Path:
    """Write ``out/report.html`` from a demo summary."""
    out = Path(out)
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>cadalign demo</title><style>{CSS}</style>"
        "</head><body><h1>cadalign demo</h1>",
        f"<p>Scene: {html.escape(summary['scene'])}</p>",
    ]
    status = [
        {"stage": k, "status": v["status"], "seconds": v.get("seconds", "")}
        for k, v in summary["stages"].items()
    ]
    parts.append("<h2 id='stages'>Stages</h2>" + table(status))
    if summary["stages"].get("sim", {}).get("status") == "done":
        parts.append(_sim_section(out, summary["stages"]["sim"]))
    build = summary["stages"].get("build-dataset", {})
    if build.get("status") == "done" and build.get("vs_truth"):
        rows = [{"ground truth": k, "coverage %": 100 * v["coverage"], "AbsRel": v["abs_rel"], "δ1": v["delta1"]}
                for k, v in build["vs_truth"]["depth"].items()]
        parts.append("<h2 id='build'>Dataset: CAD depth vs SfM depth against the true depth</h2>" + table(rows)
                     + img_tag(out / build["dir"] / "align" / "align.png", "alignment")
                     + img_tag(out / build["dir"] / "sfm" / "trajectory.png", "trajectory"))
    elif build.get("error"):
        parts.append(f"<h2 id='build'>Dataset</h2><pre class='pending'>{html.escape(build['error'])}</pre>")
    parts.append(
        "<h2 id='summary'>Summary (JSON)</h2><pre>"
        + html.escape(json.dumps(summary, indent=1)[:20000])
        + "</pre></body></html>"
    )
    return write_text(out / "report.html", "\n".join(parts))

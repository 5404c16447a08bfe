"""A self-contained HTML report (images inlined as base64) of a demo or benchmark run."""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

from cadalign.formats.html import CSS, img_tag, table
from cadalign.formats.html import fmt as _fmt
from cadalign.io import write_text


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


def _flat(d: dict | None, keys: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The scalar entries of ``d`` (optionally only ``keys``), for a one-row table."""
    d = d or {}
    return {k: v for k, v in d.items() if isinstance(v, int | float) and (keys is None or k in keys)}


def _train_section(out: Path, name: str, info: dict) -> str:
    m = info.get("metrics") or {}
    title = {"train-seg": "Segmentation (ResUNet)", "train-depth": "Depth (DispNet-style)",
             "train-pose": "Detector + 6-DoF pose head (Mask R-CNN)"}[name]
    head = (f"<h2 id='{name}'>{title}</h2><p>{info.get('steps')} training steps on the "
            f"{html.escape(str(info.get('dataset')))} dataset, final loss {_fmt(info.get('final_loss'))}; "
            "metrics on the held-out time block.</p>")
    if name == "train-seg":
        rows = [{"class": c, "IoU": v} for c, v in (m.get("iou") or {}).items()]
        body = table(rows) + table([_flat(m, ("miou", "miou_foreground", "pixel_accuracy"))])
    elif name == "train-depth":
        rows = [{"evaluated on": k, **_flat(v)} for k, v in (m.get("metrics") or {}).items() if isinstance(v, dict)]
        body = table(rows)
    else:
        summ = (m.get("summary") if isinstance(m, dict) else None) or {}
        body = table([_flat(summ)]) if summ else "<p class='pending'>no held-out score</p>"
    imgs = "".join(img_tag(out / f, Path(f).stem) for f in info.get("figures", [])[:2])
    return head + body + imgs


def _infer_section(out: Path, info: dict) -> str:
    rows = []
    t = info.get("timings") or {}
    tracker = "tracked" in t  # the structure tracker scores one set of poses (all three sections are it)
    for which, rep in (info.get("eval") or {}).items():
        if tracker and which != "fused":
            continue
        o = rep.get("overall", {})
        rows.append({"poses": "tracked" if tracker else which, "F1": rep.get("detection", {}).get("f1"),
                     "t err mean (m)": (o.get("t_err_m") or {}).get("mean"),
                     "R err mean (deg)": (o.get("r_err_deg") or {}).get("mean"),
                     "AR MSSD": o.get("ar_mssd"), "AR MSPD": o.get("ar_mspd")})
    trows = [{"step": k, "ms per frame": v.get("mean_ms")}
             for k, v in (t.get("stages") or t.get("per_stage") or {}).items()]
    inputs = f"<p>Inputs: {html.escape(str(info['inputs']))}.</p>" if info.get("inputs") else ""
    tracked = (f"<p>{t['tracked']} of {t['frames']} frames tracked, {t['lost']} lost (no pose reported).</p>"
               if "tracked" in t else "")
    return (f"<h2 id='infer'>Pose inference on {info.get('frames')} held-out frames</h2>" + inputs + tracked
            + table(rows) + "<h3>Time per stage</h3>" + table(trows))


def _fuse_section(out: Path, info: dict) -> str:
    rows = []
    for which in ("gt", "pred"):
        rep = info.get(which)
        if rep:
            met = rep.get("metrics") or {}
            rows.append({"inputs": "exact depth + labels" if which == "gt" else "predicted depth + labels",
                         **_flat(met, ("completeness_within_2cm", "completeness_within_5cm", "chamfer_m",
                                       "label_accuracy", "miou")),
                         "frames/s": (rep.get("timing") or {}).get("frames_per_second")})
    imgs = "".join(img_tag(out / info["dir"] / w / "views.png", f"map {w}") for w in ("gt", "pred") if info.get(w))
    return "<h2 id='fuse'>Semantic TSDF map</h2>" + table(rows) + imgs


def _emulate_section(out: Path, info: dict) -> str:
    rows = [{"sensor": s, **_flat(info.get(s))} for s in ("lidar", "sonar") if info.get(s)]
    return ("<h2 id='emulate'>Emulated sensors (ray cast of the CAD scene)</h2>" + table(rows)
            + img_tag(out / info["dir"] / "lidar" / "lidar_class.png", "LiDAR scan by class")
            + img_tag(out / info["dir"] / "sonar" / "sonar.png", "sonar image"))


LEARNING_SECTIONS = {"train-seg": _train_section, "train-depth": _train_section, "train-pose": _train_section}


def _build_section(out: Path, build: dict) -> str:
    """CAD depth vs SfM depth (the thesis's Table 4.2), alignment and poses, and masks per part."""
    vt = build["vs_truth"]
    rows = [{"ground truth": k, "coverage %": 100 * v["coverage"], "AbsRel": v["abs_rel"], "δ1": v["delta1"]}
            for k, v in vt["depth"].items()]
    pose = vt["pose_in_camera"]
    geo = [{"alignment rotation °": vt["alignment"]["rotation_deg"],
            "alignment translation cm": 100 * vt["alignment"]["translation_m"],
            "alignment scale %": 100 * vt["alignment"]["scale_rel"],
            "object pose rotation ° (median)": pose["rotation_deg"]["median"],
            "object pose translation cm (median)": 100 * pose["translation_m"]["median"]}]
    offsets = vt.get("mask_visib_boundary_offset_px", {})
    masks = [{"part": n, "IoU (median)": iou, "outline offset px (median)": offsets.get("per_part_median", {}).get(n),
              "part width px": offsets.get("part_width_px_median", {}).get(n)}
             for n, iou in vt["mask_visib_iou"]["per_part_median"].items()]
    return ("<h2 id='build'>Dataset: CAD depth vs SfM depth against the true depth</h2>" + table(rows)
            + "<h3>Alignment and object poses against the truth</h3>" + table(geo)
            + "<h3>Visible masks per part</h3><p>IoU punishes thin parts; the outline offset (area of "
            "disagreement / true outline length) does not.</p>" + table(masks)
            + img_tag(out / build["dir"] / "align" / "align.png", "alignment")
            + img_tag(out / build["dir"] / "sfm" / "trajectory.png", "trajectory"))


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
        parts.append(_build_section(out, build))
    elif build.get("error"):
        parts.append(f"<h2 id='build'>Dataset</h2><pre class='pending'>{html.escape(build['error'])}</pre>")
    for name, info in summary["stages"].items():
        if name in ("sim", "build-dataset"):
            continue
        if info.get("status") != "done":
            parts.append(f"<h2 id='{name}'>{html.escape(name)}</h2><pre class='pending'>"
                         f"{html.escape(info.get('status', ''))}\n{html.escape(info.get('error', ''))}</pre>")
        elif name in LEARNING_SECTIONS:
            parts.append(LEARNING_SECTIONS[name](out, name, info))
        elif name == "infer":
            parts.append(_infer_section(out, info))
        elif name == "fuse":
            parts.append(_fuse_section(out, info))
        elif name == "emulate":
            parts.append(_emulate_section(out, info))
    parts.append(
        "<h2 id='summary'>Summary (JSON)</h2><pre>"
        + html.escape(json.dumps(summary, indent=1)[:20000])
        + "</pre></body></html>"
    )
    return write_text(out / "report.html", "\n".join(parts))

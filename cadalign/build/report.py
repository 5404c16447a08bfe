"""A built dataset against the simulator's exact truth: alignment, CAD depth vs SfM depth, masks, poses.

Valid when the dataset was built from a simulator capture with the same scene spec as ``--cad``, so the
CAD frame is the simulator's world frame. Frames are matched by name (the simulator's ``NNNNNN.png``).
"""

from __future__ import annotations

import html
import json
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.formats.bop import BopScene, decode_depth
from cadalign.formats.html import CSS, img_tag, table
from cadalign.geometry import umeyama
from cadalign.io import read_image, read_json, write_text
from cadalign.metrics.dataset import boundary_offset_px, depth_errors, mask_iou, pose_errors, sim3_errors
from cadalign.sfm.report import camera_centres
from cadalign.types import Sim3

SIM_SCENE = Path("gt") / "sim" / "000000"


def true_cad_from_sfm(cameras_sfm: dict[str, dict], cameras_true: dict[str, dict]) -> Sim3:
    """The Sim3 mapping SfM camera centres onto the true ones (Umeyama with scale over common frames)."""

    common = sorted(set(cameras_sfm) & set(cameras_true))
    _, src, _ = camera_centres({"frames": {n: cameras_sfm[n] for n in common}})
    _, dst, _ = camera_centres({"frames": {n: cameras_true[n] for n in common}})
    return umeyama(src, dst, with_scale=True)


def _summary(values: list[float]) -> dict[str, float]:
    v = np.asarray([x for x in values if np.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return {"n": 0}
    return {
        "n": int(v.size),
        "median": float(np.median(v)),
        "mean": float(v.mean()),
        "min": float(v.min()),
        "max": float(v.max()),
    }


def evaluate_against_sim(
    scene_dir: Path,
    sim_dir: Path,
    frame_names: dict[int, str],
    cad_from_sfm: Sim3,
    cameras_sfm: dict[str, dict],
    structure: Any,
    sfm_dir: Path,
) -> dict[str, Any]:
    """Errors of the built ground truth against the simulator's; see the module doc for when this holds."""
    sim_scene_dir = Path(sim_dir) / SIM_SCENE
    truth, built = BopScene(sim_scene_dir), BopScene(scene_dir)
    true_T = true_cad_from_sfm(cameras_sfm, read_json(sim_scene_dir / "cameras.json")["frames"])
    pts = np.concatenate([o.T_world_from_obj.apply(structure.models[o.obj_id].vertices_m) for o in structure.objects])
    at = cad_from_sfm.inverse().apply(pts[:: max(1, len(pts) // 20000)])
    sim_map = read_json(sim_scene_dir / "objects.json")["gt_index_to_object"]
    built_map = read_json(Path(scene_dir) / "objects.json")["gt_index_to_object"]
    depth_rows = {"cad_depth": [], "sfm_depth": []}
    agg: dict[str, dict[str, list[float]]] = {k: {"coverage": [], "abs_rel": [], "delta1": []} for k in depth_rows}
    ious: dict[str, list[float]] = {}
    offsets: dict[str, list[tuple[float, float]]] = {}
    rot_err, trans_err = [], []
    names = [o.name for o in structure.objects]
    for k, name in frame_names.items():
        sim_id = int(Path(name).stem)
        true_d = truth.depth_m(sim_id)
        structure_px = read_image(sim_scene_dir / "class" / name, unchanged=True) > 0
        for key, pred in (("cad_depth", built.depth_m(k)), ("sfm_depth", _sfm_depth(scene_dir, k))):
            e = depth_errors(pred, true_d, structure_px)
            for m in agg[key]:
                agg[key][m].append(e[m])
        t_frame, b_frame = truth.frame(sim_id), built.frame(k)
        b_index = {obj: g for g, obj in enumerate(built_map[str(k)])}
        for g, obj in enumerate(sim_map[str(sim_id)]):
            if t_frame.info[g]["px_count_visib"] < 50 or obj not in b_index:
                continue
            gb = b_index[obj]
            true_mask, built_mask = truth.mask(sim_id, g), built.mask(k, gb)
            ious.setdefault(names[obj], []).append(mask_iou(true_mask, built_mask))
            offsets.setdefault(names[obj], []).append(boundary_offset_px(true_mask, built_mask))
            r, t = pose_errors(b_frame.instances[gb].T_cam_from_obj, t_frame.instances[g].T_cam_from_obj)
            rot_err.append(r)
            trans_err.append(t)
    all_iou = [v for vals in ious.values() for v in vals]
    return {
        "alignment": sim3_errors(cad_from_sfm, true_T, at),
        "depth": {
            key: {m: float(np.nanmean(v)) if v else float("nan") for m, v in d.items()} for key, d in agg.items()
        },
        "mask_visib_iou": {
            "all": _summary(all_iou),
            "per_part_median": {n: float(np.median(v)) for n, v in ious.items()},
        },
        # IoU punishes thin parts: the same outline error in pixels, and each part's mean width
        "mask_visib_boundary_offset_px": {
            "all": _summary([d for vals in offsets.values() for d, _ in vals]),
            "per_part_median": {n: float(np.median([d for d, _ in v])) for n, v in offsets.items()},
            "part_width_px_median": {n: float(np.median([w for _, w in v])) for n, v in offsets.items()},
        },
        "pose_in_camera": {"rotation_deg": _summary(rot_err), "translation_m": _summary(trans_err)},
        "frames_compared": len(frame_names),
    }


def _sfm_depth(scene_dir: Path, k: int) -> np.ndarray:
    p = Path(scene_dir) / "depth_sfm" / f"{k:06d}.png"
    return decode_depth(read_image(p, unchanged=True), 1.0) if p.is_file() else np.zeros((1, 1))


def write_build_html(out: Path, report: dict[str, Any]) -> Path:
    """``build_report.html``: alignment, timings, the CAD-vs-SfM depth table, the alignment figure."""

    parts = [
        f"<html><head><meta charset='utf-8'><style>{CSS}</style><title>cadalign dataset</title></head><body>",
        "<h1>cadalign build-dataset</h1>",
        f"<p><b>Refused: no dataset was written.</b></p><pre>{html.escape(report['refused'])}</pre>"
        if report.get("refused") else f"<p>{report['frames']} frames; splits {report['splits']}</p>",
    ]
    parts += verification_html(out, report.get("verification"))
    metrics = report["alignment"].get("metrics", {})
    parts += [
        "<h2>Alignment</h2>",
        table([{"metric": k, "value": v} for k, v in metrics.items() if isinstance(v, (int, float))]),
        img_tag(out / "align" / "align.png", "alignment"),
    ]
    edges = report.get("edge_alignment")
    if edges:
        sh = edges["shared"]
        parts += ["<h2>Edge alignment (cameras against the CAD's contours in the images)</h2>", table([
            {"step": "shared correction", "applied": sh["applied"], "deg": sh["turn_deg"], "mm": 1000 * sh["shift_m"],
             "edges": sh["edges"]},
            {"step": "per frame (median)", "applied": f"{edges['frames_refined']} of {edges['frames']}",
             "deg": edges["frame_turn_deg_median"], "mm": edges["frame_shift_mm_median"],
             "edges": "residual %s px" % (None if edges["median_abs_offset_px"] is None
                                          else round(edges["median_abs_offset_px"], 3))}])]
    vt = report.get("vs_truth")
    if vt:
        rows = [
            {"ground truth": k, "coverage %": 100 * v["coverage"], "AbsRel": v["abs_rel"], "δ1": v["delta1"]}
            for k, v in vt["depth"].items()
        ]
        parts += [
            "<h2>CAD depth vs SfM depth (against the simulator's true depth, structure pixels)</h2>",
            table(rows),
            "<h2>Against truth</h2>",
            f"<pre>{html.escape(_pretty(vt))}</pre>",
        ]
    parts += [
        "<h2>Seconds</h2>",
        table([{"step": k, "seconds": v} for k, v in report["seconds"].items()]),
        "</body></html>",
    ]
    return write_text(out / "build_report.html", "\n".join(parts))


def verification_html(out: Path, ver: dict[str, Any] | None) -> list[str]:
    """The image verification: outcome, margin, every hypothesis's evidence, and the picture of the best two."""

    if not ver:
        return []
    rows = [{"hypothesis": h["index"], "chosen": "yes" if h["index"] == ver["chosen"] else "",
             "image score": h["score"], "edge lift": h["edge"], "edge hits %": 100 * h["hit_rate"],
             "displaced hits %": 100 * h["hit_rate_shifted"], "contour samples": h["samples"],
             "free-space violations %": 100 * h["free_violation"], "rays meeting the CAD": h["free_rays"],
             "photo-consistency (reported only)": h.get("photo"), "cloud F-score": h["cloud_score"],
             "look-alike of": "" if h["same_as"] < 0 else h["same_as"]}
            for h in sorted(ver["hypotheses"], key=lambda h: -h["score"])]
    margin = "n/a (one hypothesis)" if ver["margin"] is None else f"{ver['margin']:.3f}"
    reasons = "".join(f"<li>{html.escape(r)}</li>" for r in ver["reasons"])
    return ["<h2>Verification against the images</h2>",
            f"<p>outcome <b>{ver['outcome']}</b>, hypothesis {ver['chosen']}"
            f"{' (chosen by the user)' if ver.get('user_choice') else ''}, margin to the runner-up {margin}</p>",
            f"<ul>{reasons}</ul>" if reasons else "", table(rows),
            "<p>CAD contours of the chosen (green) and runner-up (red) hypotheses over a few frames:</p>",
            img_tag(out / "verify" / "hypotheses.png", "hypotheses")]


def _pretty(obj: Any) -> str:
    return json.dumps(obj, indent=2, default=float)

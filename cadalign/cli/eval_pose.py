"""``cadalign eval pose INFER_OUT --gt SIM_DIR``: pose metrics of an ``infer`` output against ground truth."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import typer

from cadalign.cli.common import console, user_errors
from cadalign.errors import InputError
from cadalign.infer.detect import frame_ids, resolve_scene_dir
from cadalign.io import read_json
from cadalign.metrics.pose_eval import PoseEvalConfig


def command(
    poses: Path = typer.Argument(..., help="An 'infer' output folder (or its poses.jsonl)."),
    gt: Path = typer.Option(..., "--gt", help="Simulation folder or BOP scene with the ground truth."),
    out: Path | None = typer.Option(None, "--out", help="Folder for eval.json/eval.md (default: beside poses)."),
    min_box_side_px: float = typer.Option(
        0.0, "--min-box-side-px", min=0.0,
        help="Ground-truth parts whose visible box's shorter side is below this (px) are don't-care (0 = off)."),
) -> None:
    """Detection P/R/F1, t/R errors (thesis Table 4.5 layout), ADD(-S), BOP MSSD/MSPD recalls, errors by distance.

    The detector and refined sections score the reported detections of ``poses.jsonl`` with the network's boxes
    (``box_xyxy_detector`` where track completion's ``reproject`` reported another). After completion those exclude
    short tracks' detections, and their masks are the reported ones, so ``infer --gt``'s ``eval.json`` (all the
    network's detections) may differ in those sections."""
    from cadalign.infer.run import evaluate_run, read_poses  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        path = poses / "poses.jsonl" if poses.is_dir() else poses
        if not path.is_file():
            raise InputError(f"{path} not found: pass a 'cadalign infer' output folder or its poses.jsonl")
        scene = resolve_scene_dir(gt)
        records = read_poses(path)
        frames_json = path.parent / "frames.json"
        if frames_json.is_file():
            names = list(read_json(frames_json))
        else:
            names = sorted(frame_ids(scene))
            console.print(f"[yellow]{frames_json} is missing: every ground-truth frame counts (misses included)[/]")
        out_dir = out or path.parent
        out_dir.mkdir(parents=True, exist_ok=True)
        # the detector's and refined poses are those of the reported detections; completion's records count as fused
        detections = [r if r.box_detector is None else replace(r, box_xyxy=r.box_detector)
                      for r in records if r.source == "detector"]
        reports = evaluate_run(detections, names, scene, out_dir, PoseEvalConfig(min_box_side_px=min_box_side_px),
                               fused=records)
    for which, rep in reports.items():
        o = rep["overall"]
        console.print(f"{which:>9}: F1 {rep['detection']['f1']:.3f}  t_err mean {o['t_err_m']['mean']:.4f} m  "
                      f"R_err mean {o['r_err_deg']['mean']:.2f} deg  AR_MSSD {o['ar_mssd']:.3f}  "
                      f"AR_MSPD {o['ar_mspd']:.3f}")
    console.print(f"[green]written {out_dir / 'eval.json'} and eval.md[/]")

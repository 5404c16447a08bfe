"""``cadalign sfm (VIDEO|FRAMES_DIR|BAG [--topic T]) --out DIR``: camera poses, sparse model and SfM depth
with pycolmap."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import typer

from cadalign.cli.common import console, track, user_errors
from cadalign.config import merge_mappings, resolve
from cadalign.io import read_json


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``["matching.overlap=15", "frames.enhance='none'"]`` -> nested dict; values are TOML (bare words: strings)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            raise typer.BadParameter(f"{item!r}; expected KEY=VALUE, e.g. matching.overlap=15", param_hint="--set")
        try:
            value = tomllib.loads(f"v = {raw.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw.strip()
        node = out
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def _calibration(path: Path, source: Path) -> dict[str, Any]:
    """``camera`` settings (intrinsics, lens distortion) of a calibration file in any ``--calib`` format, checked
    against the size of the first frame of ``source``."""
    # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.sfm.known_camera import camera_settings, checked_calibration

    return camera_settings(checked_calibration(path, source))


def command(
    source: Path = typer.Argument(..., help="A video file, a ROS bag (.bag or ROS 2 bag folder) or a folder of "
                                  "frames (sorted by name = capture order)."),
    topic: str | None = typer.Option(None, "--topic", help="A ROS bag's image topic (default: its only one; "
                                     "'cadalign bag topics BAG' lists them)."),
    out: Path = typer.Option(..., "--out", help="Output folder (model, cameras.json, depth/, report)."),
    preset: str = typer.Option("balanced", "--preset", help="fast, balanced or accurate."),
    gt: Path | None = typer.Option(None, "--gt", help="A 'cadalign sim' output folder to evaluate against."),
    config: Path | None = typer.Option(None, "--config", help="TOML/YAML/JSON file with SfMConfig keys."),
    overrides: list[str] = typer.Option([], "--set", help="Override a key, e.g. --set matching.overlap=15."),
    calib: Path | None = typer.Option(
        None, "--calib", help="Known intrinsics and lens distortion: {\"K\": [...]} JSON (as sim writes), "
        "cameras.json, COLMAP cameras.txt, OpenCV YAML/XML or ROS CameraInfo YAML; frames are undistorted once, "
        "the K is set after self-calibrated mapping and held fixed (camera.known_intrinsics_from)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Delete SfM results of another config in --out."),
) -> None:
    """Structure from motion: frames -> SIFT -> matching -> mapping -> cameras.json, SfM depth, report."""
    from cadalign.sfm import PRESETS, SfMConfig, run  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        extra = parse_overrides(overrides)
        if calib:
            extra = merge_mappings(_calibration(calib, source), extra)
        cfg = resolve(SfMConfig, PRESETS, preset, config, extra)
        out_dir = run(cfg, source, out, overwrite=overwrite, progress=track, topic=topic)
        report = out_dir / "sfm_report.json"
        if gt is not None:
            from cadalign.evaluate.sfm import run as evaluate  # lazy: pulls cv2; keeps `cadalign --help` light

            evaluate(out_dir, gt)
    _summary(report)
    console.print(f"[green]SfM written to {out_dir}[/]")


def _summary(report_path: Path) -> None:
    r = read_json(report_path)
    console.print(
        f"registered {r['registered']}/{r['frames_in']} frames, {r['points']} points, "
        f"reprojection {r['mean_reprojection_error_px'] or 0:.2f} px, track length {r['mean_track_length'] or 0:.2f}, "
        f"{r['seconds_total']:.0f} s"
    )
    said = r.get("colmap_log") or {}
    if said.get("warnings") or said.get("errors"):
        console.print(f"COLMAP: {said['warnings']} warnings, {said['errors']} errors (colmap_log in {report_path}; "
                      "--log-level debug shows COLMAP's log)")
    if r["unregistered"]:
        console.print(f"[yellow]{len(r['unregistered'])} frames not registered (see unregistered in the report)[/]")
    if "gt" in r:
        g = r["gt"]
        console.print(
            f"vs GT: {g['registered_with_gt']}/{g['frames_gt']} registered, rotation {g['rot_err_deg_mean']:.3f} deg "
            f"mean / {g['rot_err_deg_max']:.3f} max, centre RMSE {100 * g['centre_rmse_rel']:.2f}% of "
            f"{g['median_scene_distance_m']:.2f} m, SfM depth coverage {g['sfm_depth']['coverage_mean']:.4f} "
            f"AbsRel {g['sfm_depth']['abs_rel']:.4f}"
        )

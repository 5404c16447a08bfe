"""``cadalign fuse (DS|SIM_DIR) --out MAP``: semantic TSDF or surfel map with Bayesian label fusion."""

from __future__ import annotations

from pathlib import Path

import typer

from cadalign.cli.common import console, track, user_errors
from cadalign.config import resolve
from cadalign.fuse.config import PRESETS, FuseConfig
from cadalign.io import read_json


def command(
    source: Path = typer.Argument(..., help="A `cadalign sim` output, a `build-dataset` output or dataset folder, "
                                            "or a BOP scene folder."),
    out: Path = typer.Option(..., "--out", help="Output folder (map.npz, mesh.ply, points.ply, views.png, "
                                                "fuse_report.json)."),
    depth: str = typer.Option("gt", "--depth", help="gt | pred | sfm (sfm: a built dataset's depth_sfm/)."),
    labels: str = typer.Option("gt", "--labels", help="gt | pred."),
    model_seg: Path | None = typer.Option(None, "--model-seg", help="A `cadalign train seg` run (for --labels pred)."),
    model_depth: Path | None = typer.Option(None, "--model-depth",
                                            help="A `cadalign train depth` run (for --depth pred)."),
    voxel: float | None = typer.Option(None, "--voxel", min=1e-4, help="Voxel size in metres (preset: 0.02)."),
    method: str | None = typer.Option(None, "--method", help="tsdf | surfel (preset: tsdf)."),
    preset: str = typer.Option("default", "--preset", help="default | fast | fine | realtime | surfel."),
    config: Path | None = typer.Option(None, "--config", help="TOML/YAML with overrides of the preset."),
    split: str | None = typer.Option(None, "--split", help="Only this split of a built dataset (train/val/test)."),
    max_frames: int | None = typer.Option(None, "--max-frames", min=1, help="Fuse only the first N frames."),
    ids: str | None = typer.Option(None, "--ids", help="Only image ids A <= id < B, written A:B (held-out frames)."),
    classes: Path | None = typer.Option(None, "--classes", help="JSON {obj_id: class name} for a plain BOP scene "
                                        "(default: its objects.json, else one class per object id)."),
    no_eval: bool = typer.Option(False, "--no-eval", help="Skip the metrics against the CAD truth."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace results made with another config."),
) -> None:
    """Fuse posed depth and class probabilities into a labelled 3D map (mesh, point cloud, map file, report)."""
    from cadalign.fuse.run import REPORT, run  # lazy: pulls cv2; keeps `cadalign --help` light

    id_range = None
    if ids is not None:
        try:
            a, b = (int(x) for x in ids.split(":"))
        except ValueError:
            raise typer.BadParameter(f"{ids!r}; expected A:B, e.g. 41:61", param_hint="--ids") from None
        id_range = (a, b)
    overrides = {k: v for k, v in {"voxel_m": voxel, "method": method}.items() if v is not None}
    with user_errors():
        cfg = resolve(FuseConfig, PRESETS, preset, config, overrides)
        path = run(cfg, source, out, depth=depth, labels=labels, seg_model=model_seg, depth_model=model_depth,
                   split=split, max_frames=max_frames, id_range=id_range, with_eval=not no_eval, overwrite=overwrite,
                   progress=track, classes=classes)
    report = read_json(path / REPORT)
    t = report["timing"]
    fps = f"{t['frames_per_second']:.2f} frames/s" if t["frames_per_second"] else "nothing new to fuse"
    console.print(f"{report['method']}: {t['frames']} frames, {fps}; mesh {report['map']['mesh_vertices']} vertices"
                  + ("; no label truth in the scene: geometry only" if report["labels"] == "none" else ""))
    m = report.get("metrics")
    if m:
        console.print(f"visible CAD within 2 cm {100 * m['completeness_within_2cm']:.1f}% (5 cm "
                      f"{100 * m['completeness_within_5cm']:.1f}%), label accuracy {m['label_accuracy']:.3f}, "
                      f"mIoU {m['miou']:.3f}")
    console.print(f"[green]map written to {path}[/]")

"""``cadalign build-dataset SOURCE --cad CAD --out DIR``: video + CAD -> metric dense BOP dataset."""

from __future__ import annotations

from pathlib import Path

import typer

from cadalign.cli.common import console, track, user_errors


def command(
    source: Path = typer.Argument(..., help="ROV video file or a folder of frames."),
    cad: Path = typer.Option(..., "--cad", help="Scene spec (TOML/YAML: parts, poses, classes) or one CAD mesh."),
    out: Path = typer.Option(..., "--out", help="Output folder (sfm/, align/, dataset/, build_report.*)."),
    preset: str = typer.Option("balanced", "--preset", help="fast | balanced | accurate (SfM and alignment)."),
    init: Path | None = typer.Option(None, "--init", help="Picked point pairs (JSON) for the coarse alignment."),
    gt: Path | None = typer.Option(None, "--gt", help="Simulator output folder: report errors against truth."),
    cad_unit: str | None = typer.Option(None, "--cad-unit", help="Unit of a CAD mesh file: m, cm, mm or in."),
    calib: Path | None = typer.Option(
        None, "--calib", help="Known intrinsics: a calibration.json {\"K\": [...]} (as sim writes) or a "
        "cameras.json; held fixed after mapping and in the CAD-anchored refinement."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace results made with another config."),
    executor: str = typer.Option("local", "--executor",
                                 help="Where frames are rendered: local (this process, no Ray) | ray (Ray tasks)."),
    ray_address: str | None = typer.Option(None, "--ray-address",
                                           help="Ray cluster address (e.g. ray://head:10001); default: $RAY_ADDRESS, "
                                           "else a Ray instance started on this machine. Needs --executor ray."),
    workers: int | None = typer.Option(None, "--workers",
                                       help="Ray: most tasks in flight at once (a local Ray instance also gets this "
                                       "many CPUs); default: all CPUs (local), 2 tasks per CPU in flight."),
) -> None:
    """Frames -> SfM -> CAD alignment (Sim3) -> per-frame CAD depth, normals, masks, poses -> BOP dataset."""
    from cadalign.build_dataset import build_dataset
    from cadalign.scale import executor_config, make_executor

    with user_errors():
        runner = make_executor(executor_config(executor, ray_address, workers))
        out_dir = build_dataset(source, cad, out, preset=preset, picks=init, gt=gt, cad_unit=cad_unit,
                                calib=calib, overwrite=overwrite, progress=track, executor=runner)
    console.print(f"[green]dataset written to {out_dir / 'dataset'}; report {out_dir / 'build_report.html'}[/]")

"""``cadalign build-dataset SOURCE --cad CAD --out DIR``: video + CAD -> metric dense BOP dataset."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from cadalign.cli.common import console, track, user_errors
from cadalign.cli.sfm import parse_overrides
from cadalign.errors import ConfigError

if TYPE_CHECKING:
    from cadalign.build.executor import ExecutorConfig


def command(
    source: Path = typer.Argument(..., help="ROV video file, ROS bag (.bag or ROS 2 bag folder) or a folder of "
                                  "frames; or a jobs file (TOML/YAML of "
                                  "\\[\\[video]] entries, see docs/scaling.md) to build many videos into OUT/<name>/."),
    cad: Path = typer.Option(..., "--cad", help="Scene spec (TOML/YAML: parts, poses, classes) or one CAD mesh."),
    out: Path = typer.Option(..., "--out", help="Output folder (sfm/, align/, dataset/, build_report.*)."),
    preset: str = typer.Option("balanced", "--preset", help="fast | balanced | accurate (SfM and alignment)."),
    init: Path | None = typer.Option(None, "--init", help="Picked point pairs (JSON) for the coarse alignment."),
    hypothesis: int | None = typer.Option(
        None, "--hypothesis", help="Use alignment hypothesis N (numbered in OUT/verify/hypotheses.png and "
        "verify.json) after a refusal: no margin over the others is required, but the images must still confirm it."),
    roi: Path | None = typer.Option(None, "--roi", help="Region of interest (JSON: a box in the SfM frame or clicks "
                                    "round the CAD in a few frames, see cadalign.align.roi); the alignment uses only "
                                    "the SfM points there."),
    no_verify: bool = typer.Option(False, "--no-verify", help="Skip the image verification of the alignment "
                                   "(trust the point-cloud gates alone; a wrong placement may then go unnoticed)."),
    gt: Path | None = typer.Option(None, "--gt", help="Simulator output folder: report errors against truth."),
    cad_unit: str | None = typer.Option(None, "--cad-unit", help="Unit of a CAD mesh file: m, cm, mm or in."),
    calib: Path | None = typer.Option(
        None, "--calib", help="Known intrinsics and lens distortion: {\"K\": [...]} JSON (as sim writes), "
        "cameras.json, COLMAP cameras.txt, OpenCV YAML/XML or ROS CameraInfo YAML; frames are undistorted once, "
        "the K is held fixed after mapping and in the CAD-anchored refinement."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace results made with another config."),
    topic: str | None = typer.Option(None, "--topic", help="A ROS bag's image topic (default: its only one; "
                                     "'cadalign bag topics BAG' lists them)."),
    sfm_set: list[str] = typer.Option([], "--sfm-set", help="Override an SfM setting of the preset, e.g. "
                                      "--sfm-set matching.overlap=15 (keys as 'cadalign sfm --set')."),
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
    from cadalign.build import executor_config, make_executor  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.build.run import DEFAULT_VERIFY, build_dataset  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.build.videos import JOBS_SUFFIXES  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        cfg = executor_config(executor, ray_address, workers)
        if source.suffix.lower() in JOBS_SUFFIXES and source.is_file():
            if sfm_set:
                raise ConfigError(f"--sfm-set is for one video; a jobs file ({source}) builds each video with its "
                                  "preset's SfM settings")
            _many(source, cad, out, preset, init, gt, cad_unit, calib, overwrite, cfg)
            return
        runner = make_executor(cfg)
        out_dir = build_dataset(source, cad, out, preset=preset, picks=init, gt=gt, cad_unit=cad_unit,
                                calib=calib, overwrite=overwrite, progress=track, executor=runner,
                                sfm_set=parse_overrides(sfm_set), topic=topic, hypothesis=hypothesis,
                                verify=None if no_verify else DEFAULT_VERIFY, roi=roi)
    console.print(f"[green]dataset written to {out_dir / 'dataset'}; report {out_dir / 'build_report.html'}[/]")


def _many(jobs_file: Path, cad: Path, out: Path, preset: str, init: Path | None, gt: Path | None,
          cad_unit: str | None, calib: Path | None, overwrite: bool, cfg: ExecutorConfig) -> None:
    """Build every video of a jobs file; exit 1 when any failed (the others are kept)."""
    from cadalign.build import make_executor  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.build.videos import REPORT, build_videos, read_jobs  # lazy: pulls cv2; keeps `cadalign --help` light

    if init is not None or gt is not None:
        raise ConfigError(f"--init and --gt belong to one video: put them as init = / gt = under its [[video]] in "
                          f"{jobs_file}")
    jobs = read_jobs(jobs_file, cad=cad, calib=calib, cad_unit=cad_unit)
    make_executor(cfg)  # refuses ray when it is not installed, before any work
    results = build_videos(jobs, out, cfg, preset=preset, overwrite=overwrite, progress=track)
    for r in results:
        console.print(f"{'[green]ok' if r.ok else '[red]failed'}[/] {r.name}: "
                      f"{f'{r.frames} frames in {r.out}' if r.ok else r.error}")
    failed = [r.name for r in results if not r.ok]
    console.print(f"{len(results) - len(failed)}/{len(results)} videos built; report {out / REPORT}")
    if failed:
        raise typer.Exit(code=1)

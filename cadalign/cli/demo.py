"""``cadalign demo --out DIR``: the main job on the embedded default scene.

Stages run in order and reuse finished work on a re-run; a failed stage is reported
in the summary and makes the command exit 1.
"""

from __future__ import annotations

from pathlib import Path

import typer

from cadalign.cli.common import console, track, user_errors
from cadalign.cli.sim import _resolution


def command(
    out: Path = typer.Option(Path("runs/demo"), "--out", help="Output folder."),
    scene: Path | None = typer.Option(None, "--scene", help="Scene spec; default: the embedded default scene."),
    frames: int | None = typer.Option(None, "--frames", min=1, help="Override the number of frames."),
    resolution: str | None = typer.Option(None, "--resolution", help="WIDTHxHEIGHT override."),
) -> None:
    """Run the whole pipeline on the embedded default scene and write a summary."""
    from cadalign.demo.run import run_demo  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        summary = run_demo(out, scene=scene, frames=frames, resolution=_resolution(resolution), progress=track)
    for stage, info in summary["stages"].items():
        console.print(f"  {stage:<14} {info['status']}")
    console.print(f"[green]demo written to {out} (summary.json, report.html)[/]")
    if not summary["ok"]:
        console.print("[red]a stage failed; see report.html[/]")
        raise typer.Exit(code=1)

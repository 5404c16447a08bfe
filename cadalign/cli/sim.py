"""``cadalign sim SCENE.toml --out DIR``: render a synthetic underwater scene with exact ground truth."""

from __future__ import annotations

from pathlib import Path

import typer

from cadalign.cli.common import console, track, user_errors


def _resolution(value: str | None) -> tuple[int, int] | None:
    if value is None:
        return None
    try:
        w, h = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"{value!r}; expected WIDTHxHEIGHT, e.g. 640x480") from None
    if w < 8 or h < 8:
        raise typer.BadParameter(f"{value!r}; width and height must be at least 8")
    return w, h


def command(
    scene: Path = typer.Argument(..., help="Scene spec (TOML/YAML), e.g. datasets/scenes/default.toml."),
    out: Path = typer.Option(..., "--out", help="Output folder (frames, video, BOP ground truth, report)."),
    frames: int | None = typer.Option(None, "--frames", min=1, help="Number of frames (overrides the scene)."),
    resolution: str | None = typer.Option(None, "--resolution", help="WIDTHxHEIGHT (overrides the scene)."),
    seed: int | None = typer.Option(None, "--seed", help="Random seed (overrides the scene)."),
    no_video: bool = typer.Option(False, "--no-video", help="Skip writing video.mp4."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Delete results of another config in --out."),
) -> None:
    """Render a synthetic underwater scene: frames, video, BOP ground truth and a contact sheet."""
    from cadalign.sim.run import simulate  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        out_dir = simulate(scene, out, frames=frames, resolution=_resolution(resolution), seed=seed,
                           overwrite=overwrite, video=not no_video, progress=track)
    console.print(f"[green]simulation written to {out_dir}[/]")

"""``cadalign train seg|depth DS --out RUN``: train the dense networks (the pose engineer adds ``pose``)."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from cadalign.cli.common import console, user_errors
from cadalign.config import resolve

app = typer.Typer(help="Train the segmentation, depth or detection+pose networks.", no_args_is_help=True)

DS_HELP = "Dataset root with splits.json (trains on its train ids) or a BOP scene folder (e.g. gt/sim/000000)."


def overrides(steps: int | None, seed: int | None) -> dict[str, Any]:
    """Command-line overrides of the loop settings."""
    loop = {k: v for k, v in (("steps", steps), ("seed", seed)) if v is not None}
    return {"loop": loop} if loop else {}


@contextlib.contextmanager
def progress_bar(description: str) -> Iterator[Callable[[int, int, dict[str, float]], None]]:
    """A rich progress bar fed by the training loop's ``progress(step, total, metrics)`` callback."""

    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  TextColumn("{task.fields[info]}"), console=console) as bar:
        task = bar.add_task(description, total=None, info="")

        def update(step: int, total: int, metrics: dict[str, float]) -> None:
            info = " ".join(f"{k} {v:.4g}" for k, v in list(metrics.items())[:3])
            bar.update(task, completed=step, total=total, info=info)

        yield update


def _report(result: Any, out: Path) -> None:
    state = "interrupted (continue with --resume)" if result.interrupted else "done"
    console.print(f"[green]{state}: {result.steps_done} steps, last loss {result.final_loss:.4g}, "
                  f"{result.seconds:.0f} s -> {out}[/]")
    if result.interrupted:  # a non-zero code, so `train ... && eval ...` does not go on with a half-trained net
        raise typer.Exit(code=130)


@app.command("seg")
def seg(
    ds: Path = typer.Argument(..., help=DS_HELP),
    out: Path = typer.Option(..., "--out", help="Run folder: checkpoints/, metrics.json, loss.png, train_config.json."),
    preset: str = typer.Option("fast", "--preset", help="fast | balanced | accurate."),
    config: Path | None = typer.Option(None, "--config", help="TOML/YAML overrides of the preset (see training/)."),
    resume: bool = typer.Option(False, "--resume", help="Continue from OUT/checkpoints/last.pt."),
    steps: int | None = typer.Option(None, "--steps", min=1, help="Override the preset's optimiser steps."),
    seed: int | None = typer.Option(None, "--seed", help="Override the seed."),
    split: str = typer.Option("train", "--split", help="Frames to train on: train | val | test | all."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the run in OUT (its checkpoints and records)."),
    device: str = typer.Option("cpu", "--device", help="torch device, e.g. cpu or cuda."),
) -> None:
    """Train the ResUNet segmentation network (classes from the dataset's objects.json)."""
    from cadalign.train.seg import PRESETS, SegTrainConfig, train_seg  # lazy: pulls cv2, kornia, torch

    with user_errors():
        cfg = resolve(SegTrainConfig, PRESETS, preset, config, overrides(steps, seed))
        with progress_bar("train seg") as progress:
            result = train_seg(cfg, ds, out, split=split, resume=resume, overwrite=overwrite, device=device,
                               progress=progress)
    _report(result, out)


@app.command("depth")
def depth(
    ds: Path = typer.Argument(..., help=DS_HELP),
    out: Path = typer.Option(..., "--out", help="Run folder: checkpoints/, metrics.json, loss.png, train_config.json."),
    preset: str = typer.Option("fast", "--preset", help="fast | balanced | accurate."),
    config: Path | None = typer.Option(None, "--config", help="TOML/YAML overrides of the preset (see training/)."),
    resume: bool = typer.Option(False, "--resume", help="Continue from OUT/checkpoints/last.pt."),
    steps: int | None = typer.Option(None, "--steps", min=1, help="Override the preset's optimiser steps."),
    seed: int | None = typer.Option(None, "--seed", help="Override the seed."),
    split: str = typer.Option("train", "--split", help="Frames to train on: train | val | test | all."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the run in OUT (its checkpoints and records)."),
    device: str = typer.Option("cpu", "--device", help="torch device, e.g. cpu or cuda."),
) -> None:
    """Train the DispNet-style metric depth network (masked loss on valid depth pixels)."""
    from cadalign.train.depth import PRESETS, DepthTrainConfig, train_depth  # lazy: pulls cv2, kornia, torch

    with user_errors():
        cfg = resolve(DepthTrainConfig, PRESETS, preset, config, overrides(steps, seed))
        with progress_bar("train depth") as progress:
            result = train_depth(cfg, ds, out, split=split, resume=resume, overwrite=overwrite, device=device,
                                 progress=progress)
    _report(result, out)


@app.command("pose")
def pose(
    ds: Path = typer.Argument(..., help=DS_HELP),
    out: Path = typer.Option(..., "--out", help="Run folder: checkpoints/, metrics.json, loss.png, eval_heldout.json."),
    preset: str = typer.Option("fast", "--preset", help="fast (320x240, ResNet-18) | balanced | accurate."),
    pose_param: str | None = typer.Option(None, "--pose", help="Pose parameterisation: thesis | improved."),
    config: Path | None = typer.Option(None, "--config", help="TOML/YAML overrides of the preset (see training/)."),
    resume: bool = typer.Option(False, "--resume", help="Continue from OUT/checkpoints/last.pt."),
    steps: int | None = typer.Option(None, "--steps", min=1, help="Override the preset's optimiser steps."),
    seed: int | None = typer.Option(None, "--seed", help="Override the seed."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the run in OUT (its checkpoints and records)."),
    device: str = typer.Option("cpu", "--device", help="torch device, e.g. cpu or cuda."),
) -> None:
    """Train Mask R-CNN with the 6-DoF pose head; scores the held-out (val + test) frames at the end."""
    from cadalign.train.pose import PRESETS, PoseTrainConfig, run  # lazy: pulls cv2, kornia, torch

    with user_errors():
        extra = overrides(steps, seed)
        if pose_param is not None:
            extra["model"] = {"pose": pose_param}
        cfg = resolve(PoseTrainConfig, PRESETS, preset, config, extra)
        with progress_bar(f"train pose ({cfg.model.pose})") as progress:
            result = run(cfg, ds, out, resume=resume, overwrite=overwrite, device=device, progress=progress)
    _report(result, out)

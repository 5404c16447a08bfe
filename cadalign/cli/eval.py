"""``cadalign eval seg|depth --model RUN DS --out DIR``: metrics JSON + PNG panels (the pose engineer adds ``pose``)."""

from __future__ import annotations

from pathlib import Path

import typer

from cadalign.cli import eval_pose
from cadalign.cli.common import console, user_errors
from cadalign.config import from_dict
from cadalign.metrics.depth import DepthEvalConfig

app = typer.Typer(help="Evaluate trained networks on a dataset split (metrics JSON and figures).",
                  no_args_is_help=True)

DS_HELP = "Dataset root with splits.json or a BOP scene folder (same as for training)."
app.command("pose")(eval_pose.command)


@app.command("seg")
def seg(
    ds: Path = typer.Argument(..., help=DS_HELP),
    model: Path = typer.Option(..., "--model", help="Training run folder (or a checkpoint .pt in it)."),
    out: Path = typer.Option(..., "--out", help="Folder for seg_metrics.json and seg_*.png."),
    split: str = typer.Option("test", "--split", help="train | val | test | all."),
    device: str = typer.Option("cpu", "--device", help="torch device."),
    figures: int = typer.Option(4, "--figures", min=0, help="Number of frames drawn as PNG panels."),
    flip_tta: bool = typer.Option(False, "--flip-tta", help="Average each frame with its mirror (2x time)."),
) -> None:
    """Per-class IoU, mIoU and pixel accuracy of a segmentation model."""
    from cadalign.evaluate.dense import evaluate_seg  # lazy: pulls torch

    with user_errors():
        res = evaluate_seg(model, ds, out, split=split, device=device, n_vis=figures, flip_tta=flip_tta)
    ious = ", ".join(f"{k} {'-' if v is None else f'{v:.3f}'}" for k, v in res.metrics["iou"].items())
    console.print(f"mIoU {res.metrics['miou']:.3f}, pixel accuracy {res.metrics['pixel_accuracy']:.3f}; IoU: {ious}")
    console.print(f"[green]written {res.metrics_path}[/]")


@app.command("depth")
def depth(
    ds: Path = typer.Argument(..., help=DS_HELP),
    model: Path = typer.Option(..., "--model", help="Training run folder (or a checkpoint .pt in it)."),
    out: Path = typer.Option(..., "--out", help="Folder for depth_metrics.json and depth_*.png."),
    split: str = typer.Option("test", "--split", help="train | val | test | all."),
    device: str = typer.Option("cpu", "--device", help="torch device."),
    figures: int = typer.Option(4, "--figures", min=0, help="Number of frames drawn as PNG panels."),
    max_depth: float = typer.Option(80.0, "--max-depth", help="Cap, metres: farther ground truth is ignored."),
    min_depth: float = typer.Option(1e-3, "--min-depth", help="Nearer ground truth is ignored, metres."),
    alignment: str = typer.Option("none", "--alignment", help="none (metric) | median (per-frame scaling)."),
) -> None:
    """Eigen depth metrics (AbsRel, SqRel, RMSE, RMSElog, delta<1.25^k), over all valid pixels and per class."""
    from cadalign.evaluate.dense import evaluate_depth  # lazy: pulls torch

    with user_errors():
        cfg = from_dict(DepthEvalConfig, {"max_depth_m": max_depth, "min_depth_m": min_depth, "alignment": alignment},
                        source="command line")
        res = evaluate_depth(model, ds, out, split=split, device=device, cfg=cfg, n_vis=figures)
    for name, m in res.metrics["metrics"].items():
        if m["frames"]:
            console.print(f"{name:<12} AbsRel {m['abs_rel']:.4f}  RMSE {m['rmse']:.4f} m  delta1 {m['delta1']:.4f}")
    console.print(f"[green]written {res.metrics_path}[/]")

"""``cadalign align POINTS --cad CAD --out DIR``: CAD <-> SfM registration with scale (writes align.json)."""

from __future__ import annotations

from pathlib import Path

import typer

from cadalign.align import PRESETS, AlignConfig, run
from cadalign.cli.common import console, user_errors
from cadalign.config import resolve


def command(
    points: Path = typer.Argument(..., help="SfM points: COLMAP sparse model folder, PLY/PCD/XYZ or .npy (N, 3)."),
    cad: Path = typer.Option(..., "--cad", help="Scene spec (TOML/YAML: parts, poses, classes) or one CAD mesh."),
    out: Path = typer.Option(..., "--out", help="Output folder (align.json, align.png)."),
    preset: str = typer.Option("balanced", "--preset", help="fast | balanced | accurate."),
    config: Path | None = typer.Option(None, "--config", help="TOML/YAML with overrides of the preset."),
    init: Path | None = typer.Option(None, "--init", help="Picked point pairs (JSON) for the coarse alignment."),
    prior: Path | None = typer.Option(None, "--prior", help="A prior cad_from_sfm (an align.json or Sim3 JSON)."),
    cad_unit: str | None = typer.Option(None, "--cad-unit", help="Unit of a CAD mesh file: m, cm, mm or in."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace results made with another config."),
) -> None:
    """Align the CAD to the SfM cloud (global + Sim(3) ICP); a failed quality gate writes nothing."""
    from cadalign.sim.structure import load_structure  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        cfg = resolve(AlignConfig, PRESETS, preset, config, {})
        structure = load_structure(cad, cad_unit)
        parts = [(structure.models[o.obj_id], o.T_world_from_obj) for o in structure.objects]
        path = run(cfg, points, parts, out, picks=init, prior=prior, overwrite=overwrite)
    console.print(f"[green]alignment written to {path}[/]")

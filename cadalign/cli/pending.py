"""Commands whose stage has not landed yet: they say so and which issue tracks them.

Each command moves to its own file when its stage lands.
"""

from __future__ import annotations

import typer

from cadalign.cli.common import console

PENDING: dict[str, tuple[str, int]] = {
    "train": ("Train the segmentation, depth or detection+pose networks.", 6),
    "infer": ("Per-frame 6-DoF poses of the CAD parts on ROV video.", 7),
    "fuse": ("Fuse depth, labels and poses into a semantic TSDF or surfel map.", 8),
    "emulate": ("Emulate LiDAR, sonar or novel views by ray casting.", 9),
    "bench": ("Accuracy-versus-time benchmark of every stage.", 10),
}


def _make(name: str, summary: str, issue: int) -> typer.models.CommandInfo:
    def command(ctx: typer.Context) -> None:
        console.print(f"[yellow]'cadalign {name}' is not available in this version yet (tracked in issue {issue}).[/]")
        raise typer.Exit(code=2)

    command.__doc__ = f"{summary} [not available yet: issue {issue}]"
    return command


def register(app: typer.Typer, skip: set[str]) -> None:
    """Add a placeholder for each pending command not in ``skip``."""
    for name, (summary, issue) in PENDING.items():
        if name not in skip:
            app.command(name, context_settings={"allow_extra_args": True, "ignore_unknown_options": True})(
                _make(name, summary, issue)
            )

"""``cadalign bench STAGE``: accuracy and speed of a stage, as ratios against a baseline measured in the same run."""

from __future__ import annotations

from pathlib import Path

import typer

from cadalign.cli.common import console, track, user_errors
from cadalign.cli.sim import _resolution

app = typer.Typer(help="Accuracy-versus-time benchmarks; each writes JSON and plots.", no_args_is_help=True)


@app.command("sim")
def sim(
    scene: Path = typer.Argument(None, help="Scene spec; default: the embedded default scene."),
    out: Path = typer.Option(Path("runs/bench/sim"), "--out", help="Folder for bench_sim.json and bench_sim.png."),
    frames: int = typer.Option(8, "--frames", min=1, help="Frames to time (spread over the trajectory)."),
    resolution: str | None = typer.Option(None, "--resolution", help="WIDTHxHEIGHT (default: the scene's)."),
) -> None:
    """Per-frame cost of the simulator: bare render, effect-free path, each effect, all effects, writing."""
    from cadalign.eval.bench_sim import bench_sim
    from cadalign.sim.spec import default_scene_path

    with user_errors():
        r = bench_sim(scene or default_scene_path(), out, frames=frames, resolution=_resolution(resolution),
                      progress=track)
    med = r["seconds_per_frame_median"]
    console.print(f"bare render {med['bare']:.3f} s/frame; effect-free path {r['effect_free_overhead_pct']:+.1f}%; "
                  f"all effects {r['all_effects_s_per_frame']:.3f} s/frame "
                  f"({r['all_effects_with_write_s_per_frame']:.3f} with writing)")
    for name in r["effects"]:
        console.print(f"  {name:<18} {1000 * med['effect:' + name]:7.1f} ms")
    console.print(f"[green]written {out / 'bench_sim.json'} and {out / 'bench_sim.png'}[/]")

"""``cadalign bench STAGE|all --out DIR``: accuracy-versus-time sweeps (bench.json, Pareto plots, bench.html).

``bench sim`` without ``--sweep`` keeps its original meaning: the per-effect cost of the simulator against
the bare render, measured in the same run (bench_sim.json/png).
"""

from __future__ import annotations

from pathlib import Path

import typer

from cadalign.bench.fuse_timing import bench_fuse
from cadalign.bench.report import recommendations, write_bench_report
from cadalign.cli.common import console, track, user_errors
from cadalign.cli.sim import _resolution
from cadalign.config import read_mapping, resolve
from cadalign.errors import InputError
from cadalign.fuse.config import FuseConfig
from cadalign.io import write_json
from cadalign.types import Camera

app = typer.Typer(help="Accuracy-versus-time benchmarks: sweeps a stage's knobs, writes bench.json, Pareto plots "
                  "and bench.html (the setting within 5% of the best accuracy at the least time).",
                  no_args_is_help=True)

SIZE = typer.Option("small", "--size", help="tiny (seconds per stage), small (minutes), full (up to ~1 h on 2 cores).")
REPEATS = typer.Option(None, "--repeats", min=1, help="Timed runs per setting (default: the size's); medians.")
SEED = typer.Option(0, "--seed", help="Seed of the simulated data and every random choice.")
OVERWRITE = typer.Option(False, "--overwrite", help="Start over in a folder made with another size/repeats/seed.")
OUT = typer.Option(Path("runs/bench"), "--out", help="Benchmark folder (bench.json, pareto_*.png, bench.html, data/).")


def _config(size: str, repeats: int | None, seed: int):  # -> BenchConfig
    from cadalign.bench.data import size_spec  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.bench.registry import BenchConfig  # lazy: pulls cv2; keeps `cadalign --help` light

    return BenchConfig(size, repeats or size_spec(size).repeats, seed)


def _print_summary(out: Path) -> None:
    from cadalign.bench.registry import load_bench  # lazy: pulls cv2; keeps `cadalign --help` light

    for r in recommendations(load_bench(out)):
        console.print(f"  {r['stage']:<8} recommended [bold]{r['recommended setting']}[/]: "
                      f"{r['accuracy metric']} = {r['accuracy']:.4g}, {r['cost metric']} = {r['cost']:.4g}"
                      + (f" ([red]{r['failed']} failed[/])" if r["failed"] else ""))


def _run(stages: list[str], out: Path, size: str, repeats: int | None, seed: int, overwrite: bool) -> None:
    from cadalign.bench.registry import run_bench  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        run_bench(stages, out, _config(size, repeats, seed), overwrite=overwrite, progress=track)
        _print_summary(out)
    console.print(f"[green]written {out / 'bench.json'} and {out / 'bench.html'}[/]")


def _stage_command(stage: str, doc: str) -> None:
    def command(out: Path = OUT, size: str = SIZE, repeats: int | None = REPEATS, seed: int = SEED,
                overwrite: bool = OVERWRITE) -> None:
        _run([stage], out, size, repeats, seed, overwrite)

    command.__doc__ = doc
    app.command(stage)(command)


for _stage, _doc in (
    ("sfm", "SfM presets / features / matcher / mapper: rotation error vs seconds on a simulated clip."),
    ("align", "Sim(3) ICP iterations and schedule: pose error vs seconds on a synthetic cloud with a known Sim(3)."),
    ("render", "Ray-cast ground truth resolution: label agreement with a finer render vs ms per frame."),
    ("seg", "Segmentation network input scale x width (short training): mIoU vs ms per frame."),
    ("depth", "Depth network input scale x width (short training): delta1 vs ms per frame."),
    ("refine", "Pose refinement iterations: ADD error vs ms per instance."),
    ("fuse", "Fusion voxel size: Chamfer distance to the CAD vs ms per frame (frames/s in the table)."),
    ("emulate", "LiDAR rays and engine (BVH vs torch): surface gap vs seconds per scan."),
):
    _stage_command(_stage, _doc)


@app.command("infer")
def infer(
    model: Path | None = typer.Option(None, "--model", help="'cadalign train pose' run folder to time (default: a "
                                      "network trained for the size's few steps on the bench clip)."),
    frames: Path | None = typer.Option(None, "--frames", help="With --model: video or folder of frames."),
    gt: Path | None = typer.Option(None, "--gt", help="With --model: simulation folder or BOP scene with the "
                                   "frames' truth and intrinsics."),
    cad: Path | None = typer.Option(None, "--cad", help="With --model: the scene spec it was trained on."),
    depth: Path | None = typer.Option(None, "--depth", help="With --model: simulation or BOP scene with "
                                      "depth for ICP."),
    config: Path | None = typer.Option(None, "--config", help="With --model: TOML/YAML of InferConfig keys for every "
                                       "setting, e.g. enhance = \"none\" for frames already enhanced."),
    max_frames: int | None = typer.Option(None, "--max-frames", min=1, help="With --model: time at most this many "
                                          "frames."),
    out: Path = OUT, size: str = SIZE, repeats: int | None = REPEATS, seed: int = SEED, overwrite: bool = OVERWRITE,
) -> None:
    """Infer presets (detector only, fast, balanced ...): ADD(-S) recall vs ms per frame, and each preset's cost
    over the detector alone measured in the same run; per-stage ms and frames/s in bench.json."""
    from cadalign.bench.registry import run_bench  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.bench.sweeps.infer import InferSource, infer_sweep  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.infer.config import PRESETS, InferConfig  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        sweeps = None
        if model is not None:
            missing = [n for n, v in (("--frames", frames), ("--gt", gt), ("--cad", cad)) if v is None]
            if missing:
                raise InputError(f"--model {model} also needs {', '.join(missing)} (the frames to time, their truth "
                                 "and the scene spec the network was trained on)")
            overrides = dict(read_mapping(config)) if config else {}
            resolve(InferConfig, PRESETS, "fast", overrides=overrides)  # a bad key fails here, not per setting
            src = InferSource(model, frames, gt, cad, depth, overrides, max_frames)
            sweeps = {"infer": lambda data, cfg: infer_sweep(data, cfg, src)}
        elif any(v is not None for v in (frames, gt, cad, depth, config, max_frames)):
            raise InputError("--frames/--gt/--cad/--depth/--config/--max-frames go with --model RUN")
        run_bench(["infer"], out, _config(size, repeats, seed), overwrite=overwrite, progress=track, sweeps=sweeps)
        _print_infer(out)
    console.print(f"[green]written {out / 'bench.json'} and {out / 'bench.html'}[/]")


def _print_infer(out: Path) -> None:
    from cadalign.bench.registry import current_records, load_bench  # lazy: pulls cv2; keeps `cadalign --help` light

    st = load_bench(out)["stages"]["infer"]
    for r in current_records(st, st["current"]):
        if r["status"] != "done":
            console.print(f"  {r['name']:<26} [red]failed[/]: {r.get('error')}")
            continue
        m = r["metrics"]
        console.print(f"  {r['name']:<26} {m['ms_per_frame']:7.1f} ms/frame ({m['frames_per_s']:.2f} frames/s; "
                      f"detector {m['ms_detector']:.0f} / pose {m['ms_pose']:.0f} / refinement "
                      f"{m['ms_refinement']:.0f} ms), x{r['cost_ratio'] or float('nan'):.2f} the detector alone; "
                      f"ADD(-S) recall {m['add_s_01d']:.3f}, F1 {m['f1']:.3f}")


@app.command("track")
def track_speed(
    frames: Path = typer.Option(..., "--frames", help="Video or folder of frames."),
    cad: Path = typer.Option(..., "--cad", help="Scene spec of the structure."),
    calib: Path = typer.Option(..., "--calib", help="The camera's calibration (any --calib format)."),
    init_pose: Path = typer.Option(..., "--init-pose", help="Rough first-frame pose (as for 'infer')."),
    model: Path | None = typer.Option(None, "--model", help="Trained 'cadalign train pose' run for the detector "
                                      "baseline (default: the recipe's architecture with random weights)."),
    recipe: Path | None = typer.Option(None, "--recipe", help="Training recipe whose architecture the default "
                                       "baseline takes (e.g. training/pose_fast_zoom_improved.toml)."),
    max_frames: int = typer.Option(30, "--max-frames", min=2, help="Frames to time."),
    repeats: int = typer.Option(1, "--repeats", min=1, help="Time the tracker and the detector this many times, in "
                                "turn, and report the medians (each repeat is kept in bench_track.json)."),
    preset: str = typer.Option("balanced", "--preset", help="The tracker's preset: fast | balanced | accurate."),
    config: Path | None = typer.Option(None, "--config", help="TOML/YAML with overrides of the tracker preset."),
    out: Path = OUT,
) -> None:
    """The structure tracker's frames/s and restart time against the detector alone, same frames, same run."""
    from cadalign.bench.track_timing import bench_track  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.formats.calibration import read_calibration  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.infer.track.config import PRESETS, TrackRunConfig  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.infer.track.run import read_init_pose  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.infer.video import iter_frames  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.sim.structure import load_structure  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        first = next(iter(iter_frames(frames, max_frames=1)))
        h, w = first.image.shape[:2]
        lens = read_calibration(calib)
        lens.check_size(w, h, f"{frames}'s first frame")
        cfg = resolve(TrackRunConfig, PRESETS, preset, config)
        res = bench_track(frames, load_structure(cad), Camera(lens.K, w, h), read_init_pose(init_pose), model=model,
                          recipe=recipe, max_frames=max_frames, cfg=cfg.tracker, max_width=cfg.max_width,
                          repeats=repeats)
        write_json(out / "bench_track.json", res.record())
    rec = res.record()
    if rec["track_ms_cpu"] is None:
        console.print(f"[yellow]{rec['problem']}[/yellow]; {res.tracked}/{res.frames} tracked, restart "
                      f"{res.restart_ms:.0f} ms -> {out / 'bench_track.json'}")
        return
    if res.repeats:
        fps = ", ".join(f"{1e3 / r['track_ms_wall']:.1f}" for r in res.repeats)
        console.print(f"{len(res.repeats)} repeats, tracker frames/s of wall time: {fps}; the medians:")
    console.print(f"tracker {1e3 / res.track_ms:.1f} frames/s (CPU), detector alone {1e3 / res.detector_ms:.1f} "
                  f"frames/s: {res.ratio:.2f}x (wall clock: {1e3 / res.track_ms_wall:.1f} and "
                  f"{1e3 / res.detector_ms_wall:.1f} frames/s, {rec['tracker_over_detector_wall']:.2f}x); restart "
                  f"{res.restart_ms:.0f} ms; {res.tracked}/{res.frames} tracked -> {out / 'bench_track.json'}")


@app.command("fuse-labels")
def fuse_labels(
    scene: Path = typer.Argument(..., help="A BOP scene folder with depth and masks (e.g. a real RGB-D capture's "
                                 "test_targets scene, or a simulation's gt/sim/000000)."),
    frames: int = typer.Option(64, "--frames", min=2, help="Frames to time (after 2 untimed)."),
    voxel_m: float | None = typer.Option(None, "--voxel-m", help="Voxel size, metres (default: the fuse config's)."),
    out: Path = OUT,
) -> None:
    """Semantic fusion with labels against Open3D's VoxelBlockGrid alone (no labels) on your scene, interleaved
    in one run: frames/s of each and their ratio (issue 45's must-show; GT depth and labels)."""
    cfg = FuseConfig() if voxel_m is None else FuseConfig(voxel_m=voxel_m)
    with user_errors():
        r = bench_fuse(scene, cfg, frames=frames, out=out)
    console.print(f"labels: {r['frames_per_second_median']:.1f} frames/s; Open3D alone: "
                  f"{r['open3d']['frames_per_second_median']:.1f} frames/s: [bold]{r['fps_vs_open3d']:.2f}x[/] "
                  f"({r['frames_timed']} frames, {r['image']}, {r['voxel_m']} m voxels) -> {out / 'bench_fuse.json'}")


@app.command("all")
def all_stages(
    out: Path = OUT, size: str = SIZE, repeats: int | None = REPEATS, seed: int = SEED, overwrite: bool = OVERWRITE,
    skip: list[str] = typer.Option([], "--skip", help="Stage to leave out (repeatable), e.g. --skip seg."),
    robustness: bool = typer.Option(True, "--robustness/--no-robustness", help="Also run the low-visibility sweep."),
    models: Path | None = typer.Option(None, "--models", help="For robustness: folder with seg/, depth/ and/or "
                                       "pose/ training runs to score under each condition."),
) -> None:
    """Every stage's sweep (sim, sfm, align, render, seg, depth, refine, infer, fuse, emulate), then robustness."""
    from cadalign.bench.registry import STAGES  # lazy: pulls cv2; keeps `cadalign --help` light

    bad = [s for s in skip if s not in STAGES]
    if bad:
        raise typer.BadParameter(f"{bad}; allowed: {', '.join(STAGES)}", param_hint="--skip")
    _run([s for s in STAGES if s not in skip], out, size, repeats, seed, overwrite)
    if robustness:
        robust(out=out, size=size, seed=seed, models=models)


@app.command("robustness")
def robust(
    out: Path = OUT, size: str = SIZE, seed: int = SEED,
    models: Path | None = typer.Option(None, "--models", help="Optional folder with seg/, depth/ and/or pose/ "
                                       "training runs (cadalign train) to score under each condition."),
) -> None:
    """Low visibility: turbidity (Jerlov type), marine snow density and light level, >= 3 severities each;
    SfM registration rate, rotation error and image contrast (and model scores with --models) vs severity."""
    from cadalign.evaluate.robustness import run_robustness  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        rob = run_robustness(out, size=size, seed=seed, models=models, progress=track)
        write_bench_report(out)
    for r in rob["rows"]:
        m = {k: float("nan") if v is None else v for k, v in r["metrics"].items()}
        console.print(f"  {r['effect']:<11} {r['severity']:<9} registration {m.get('registration_rate', -1):.2f}  "
                      f"rotation {m.get('rel_rot_err_deg', -1):.3f} deg (frame to frame)  "
                      f"contrast {m.get('contrast', -1):.3f}")
    console.print(f"[green]written {out / 'robustness.json'} and {out / 'bench.html'}[/]")


@app.command("sim")
def sim(
    scene: Path = typer.Argument(None, help="Scene spec; default: the embedded default scene."),
    out: Path = typer.Option(Path("runs/bench/sim"), "--out", help="Folder for bench_sim.json and bench_sim.png."),
    frames: int = typer.Option(8, "--frames", min=1, help="Frames to time (spread over the trajectory)."),
    resolution: str | None = typer.Option(None, "--resolution", help="WIDTHxHEIGHT (default: the scene's)."),
    sweep: bool = typer.Option(False, "--sweep", help="Run the effects on/off sweep into OUT/bench.json instead "
                               "(default scene; uses --size/--repeats/--seed/--overwrite)."),
    size: str = SIZE,
    repeats: int | None = REPEATS,
    seed: int = SEED,
    overwrite: bool = OVERWRITE,
) -> None:
    """Per-frame cost of the simulator: bare render, effect-free path, each effect, all effects, writing.

    With --sweep: effect subsets (none ... all) as an accuracy-vs-time sweep like the other stages."""
    from cadalign.bench.sim import bench_sim  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.sim.spec import default_scene_path  # lazy: pulls cv2; keeps `cadalign --help` light

    if sweep:
        _run(["sim"], out, size, repeats, seed, overwrite)
        return
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

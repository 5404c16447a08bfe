"""``cadalign infer VIDEO|FRAMES --model RUN --cad CAD --out OUT``: per-frame 6-DoF poses of the CAD parts."""

from __future__ import annotations

from pathlib import Path

import typer

from cadalign.cli.common import console, track, user_errors


def command(
    source: Path = typer.Argument(..., help="ROV video file, ROS bag (.bag or ROS 2 bag folder) or folder of frames."),
    topic: str | None = typer.Option(None, "--topic", help="A ROS bag's image topic (default: its only one; "
                                     "'cadalign bag topics BAG' lists them)."),
    cad: Path = typer.Option(..., "--cad", help="Scene spec (TOML/YAML: parts and classes) or one CAD mesh."),
    out: Path = typer.Option(..., "--out", help="Output folder (poses.jsonl, overlay.mp4, timings.json, eval)."),
    model: Path | None = typer.Option(None, "--model", help="'cadalign train pose' run folder (the detector)."),
    oracle_gt: Path | None = typer.Option(
        None, "--oracle-gt", help="TEST/DEMO ONLY, instead of --model: ground-truth detections of this simulation "
        "with noisy poses (exercises refinement and fusion without a trained network)."),
    gt: Path | None = typer.Option(None, "--gt", help="Simulation folder or BOP scene: evaluate against its truth."),
    calib: Path | None = typer.Option(None, "--calib", help="cameras.json with intrinsics (and metric camera poses)."),
    depth: Path | None = typer.Option(
        None, "--depth", help="Depth for ICP: a simulation folder or BOP scene with depth maps, or a 'cadalign "
        "train depth' run (its predicted depth)."),
    preset: str = typer.Option("balanced", "--preset", help="none | fast | balanced | accurate."),
    config: Path | None = typer.Option(None, "--config", help="TOML/YAML with overrides of the preset."),
    refine_iters: int | None = typer.Option(None, "--refine-iters", min=0,
                                            help="Iterations of each refinement (silhouette and depth ICP)."),
    oracle_noise_t: float = typer.Option(0.03, "--oracle-noise-t", min=0, help="Oracle translation noise RMS, m."),
    oracle_noise_r: float = typer.Option(3.0, "--oracle-noise-r", min=0, help="Oracle rotation noise RMS, deg."),
    max_frames: int | None = typer.Option(None, "--max-frames", min=1, help="Process at most this many frames."),
    cad_unit: str | None = typer.Option(None, "--cad-unit", help="Unit of a CAD mesh file: m, cm, mm or in."),
    device: str = typer.Option("cpu", "--device", help="torch device of the network."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace results made with another config."),
) -> None:
    """Detect the parts, refine their poses against the CAD, fuse them over time; write poses.jsonl + overlay."""
    from cadalign.build_dataset import load_structure
    from cadalign.config import resolve
    from cadalign.errors import InputError
    from cadalign.infer import detect as det
    from cadalign.infer.pipeline import PRESETS, InferConfig
    from cadalign.infer.run import calibration_from_scene, load_calibration, run

    with user_errors():
        if (model is None) == (oracle_gt is None):
            raise InputError("pass exactly one detector: --model RUN (a trained network) or --oracle-gt SIM_DIR")
        overrides = {} if refine_iters is None else {"refine": {"silhouette_iters": refine_iters,
                                                                "depth_iters": refine_iters}}
        cfg = resolve(InferConfig, PRESETS, preset, config, overrides)
        structure = load_structure(cad, cad_unit)
        class_names = structure.class_names
        if model is not None:
            from cadalign.models.maskrcnn.detector import load_pose_model

            net, meta = load_pose_model(model, device)
            class_names = tuple(meta.get("classes", class_names))
            detector = det.TorchDetector(net, cfg.detector_score_thresh, device, cfg.tiles, cfg.nms_iou)
            info = {"kind": "network", "run": str(model), "step": meta.get("step")}
        else:
            scene = det.resolve_scene_dir(oracle_gt)
            ocfg = det.OracleConfig(noise_t_m=oracle_noise_t, noise_r_deg=oracle_noise_r, seed=cfg.refine.seed)
            detector = det.OracleDetector(scene, ocfg)
            class_names = detector.classes.names
            info = {"kind": "oracle", "note": "ground truth + noise, NOT a trained network", "scene": str(scene),
                    "noise_t_m": oracle_noise_t, "noise_r_deg": oracle_noise_r}
            console.print("[yellow]detector: ORACLE (ground-truth detections with noisy poses) - for tests and "
                          "demos of refinement/fusion only, not a trained network[/]")
        gt_scene = det.resolve_scene_dir(gt) if gt is not None else None
        from cadalign.infer.run import is_depth_run

        depth_scene = None if depth is None else depth if is_depth_run(depth) else det.resolve_scene_dir(depth)
        if calib is not None:
            cal = load_calibration(calib)
        elif oracle_gt is not None or gt_scene is not None:
            cal = calibration_from_scene(det.resolve_scene_dir(oracle_gt) if oracle_gt is not None else gt_scene)
        else:
            raise InputError("no camera intrinsics: pass --calib cameras.json (e.g. from 'cadalign sfm')")
        path = run(cfg, source, detector, structure.models, class_names, out, calib=cal, detector_info=info,
                   depth_scene=depth_scene, gt_scene=gt_scene, max_frames=max_frames, overwrite=overwrite,
                   progress=track, device=device, topic=topic)
    console.print(f"[green]poses written to {path}[/]")
    _print_summary(out)


def _print_summary(out: Path) -> None:
    from cadalign.io import read_json

    t = read_json(out / "timings.json")
    stages = ", ".join(f"{k} {v:.1f} ms" for k, v in t["stages_ms"].items())
    console.print(f"{t['frames']} frames, {t['poses']} poses; per frame: {stages} "
                  f"(all stages: {(t['pipeline_ms_per_frame'] or 0):.1f} ms wall, "
                  f"{t['stages'].get('pipeline_cpu', {}).get('mean_ms', 0):.1f} ms CPU)")
    if (out / "eval.json").is_file():
        ev = read_json(out / "eval.json")
        for which, rep in ev.items():
            o = rep["overall"]
            console.print(f"{which:>9}: F1 {rep['detection']['f1']:.3f}  t_err mean {o['t_err_m']['mean']:.4f} m  "
                          f"R_err mean {o['r_err_deg']['mean']:.2f} deg  AR_MSSD {o['ar_mssd']:.3f}  "
                          f"AR_MSPD {o['ar_mspd']:.3f}")

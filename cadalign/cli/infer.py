"""``cadalign infer VIDEO|FRAMES --model RUN --cad CAD --out OUT``: per-frame 6-DoF poses of the CAD parts."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

from cadalign.cli.common import console, track, user_errors
from cadalign.config import resolve
from cadalign.errors import InputError
from cadalign.infer import detect as det
from cadalign.io import read_json
from cadalign.testing import oracle
from cadalign.types import Camera

if TYPE_CHECKING:
    from cadalign.infer.config import InferConfig


def command(
    source: Path = typer.Argument(..., help="ROV video file, ROS bag (.bag or ROS 2 bag folder) or folder of frames."),
    topic: str | None = typer.Option(None, "--topic", help="A ROS bag's image topic (default: its only one; "
                                     "'cadalign bag topics BAG' lists them)."),
    cad: Path = typer.Option(..., "--cad", help="Scene spec (TOML/YAML: parts and classes) or one CAD mesh."),
    out: Path = typer.Option(..., "--out", help="Output folder (poses.jsonl, overlay.mp4, timings.json, eval)."),
    model: Path | None = typer.Option(None, "--model", help="'cadalign train pose' run folder (the detector)."),
    gt_poses: Path | None = typer.Option(
        None, "--gt-poses", help="Tracker: reference camera poses of a real capture, JSON {\"frames\": {name: "
        "T_cam_from_world 4x4}}: per-frame errors and their plot (truth_errors.json/.png)."),
    init_pose: Path | None = typer.Option(
        None, "--init-pose", help="Tracker start: JSON {\"T_cam_from_world\": 4x4, metres} of the first frame, "
        "rough (a navigation pose, ~0.5 m / 10 deg), or points picked in the first frame: {\"picks\": [{\"uv\": "
        "[col, row], \"xyz\": [x, y, z]}, ...]} (pixels; the same points on the CAD, metres; at least 4)."),
    nav: Path | None = typer.Option(
        None, "--nav", help="Tracker: rough navigation poses per frame (INS/USBL/DVL), JSON {\"frames\": {name: "
        "T_cam_from_world 4x4, metres}}: each bounds its frame's pose and restarts the track while lost (a "
        "simulation writes one: SIM/navigation.json)."),
    tracker: bool | None = typer.Option(
        None, "--tracker/--no-tracker", help="Track the whole structure in the RGB frames (default whenever there "
        "is no --depth and no metric camera poses in --calib)."),
    oracle_gt: Path | None = typer.Option(
        None, "--oracle-gt", help="TEST/DEMO ONLY, instead of --model: ground-truth detections of this simulation "
        "with noisy poses (exercises refinement and fusion without a trained network)."),
    gt: Path | None = typer.Option(
        None, "--gt", help="Simulation folder or BOP scene: evaluate against its truth (the tracker, given a "
        "simulation, also writes per-frame errors: truth_errors.json/.png)."),
    calib: Path | None = typer.Option(
        None, "--calib", help="Camera intrinsics and lens distortion: {\"K\": [...]} JSON, COLMAP cameras.txt, OpenCV "
        "YAML/XML, ROS CameraInfo YAML, or a cameras.json (which may add metric camera poses per frame)."),
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
    stride: int = typer.Option(1, "--stride", min=1, help="Process every N-th frame (a 25 frames/s video with "
                               "--stride 5 gives 5 poses a second; frames keep their names, as --nav needs)."),
    cad_unit: str | None = typer.Option(None, "--cad-unit", help="Unit of a CAD mesh file: m, cm, mm or in."),
    device: str = typer.Option("cpu", "--device", help="torch device of the network."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace results made with another config."),
) -> None:
    """Per-frame part poses: the structure tracker on RGB frames (the default without --depth and metric camera
    poses; started by --init-pose, --nav or --model), else the detector refined against the CAD and fused over time.
    Writes poses.jsonl + overlay; a run stopped early resumes when the same command is run again."""
    from cadalign.infer.config import PRESETS, InferConfig  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.infer.run import run  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.sim.structure import load_structure  # lazy: pulls cv2; keeps `cadalign --help` light

    with user_errors():
        use_tracker = tracker if tracker is not None else (
            depth is None and oracle_gt is None and (calib is None or not _has_metric_poses(calib)))
        if use_tracker:
            _track(source, cad, out, model, init_pose, gt, calib, max_frames, cad_unit, device, preset, config,
                   overwrite, topic, gt_poses, nav, stride)
            return
        if (model is None) == (oracle_gt is None):
            raise InputError("pass exactly one detector: --model RUN (a trained network) or --oracle-gt SIM_DIR")
        overrides = {} if refine_iters is None else {"refine": {"silhouette_iters": refine_iters,
                                                                "depth_iters": refine_iters}}
        cfg = resolve(InferConfig, PRESETS, preset, config, overrides)
        structure = load_structure(cad, cad_unit)
        detector, class_names, info = _detector(model, oracle_gt, cfg, structure.class_names, device,
                                                (oracle_noise_t, oracle_noise_r))
        gt_scene = det.resolve_scene_dir(gt) if gt is not None else None
        from cadalign.infer.run import is_depth_run  # lazy: pulls cv2; keeps `cadalign --help` light

        depth_scene = None if depth is None else depth if is_depth_run(depth) else det.resolve_scene_dir(depth)
        cal = _calibration(calib, det.resolve_scene_dir(oracle_gt) if oracle_gt is not None else gt_scene)
        path = run(cfg, source, detector, structure.models, class_names, out, calib=cal, detector_info=info,
                   depth_scene=depth_scene, gt_scene=gt_scene, max_frames=max_frames, overwrite=overwrite,
                   progress=track, device=device, topic=topic, stride=stride)
    console.print(f"[green]poses written to {path}[/]")
    _print_summary(out)


def _detector(model: Path | None, oracle_gt: Path | None, cfg: InferConfig, class_names: tuple[str, ...], device: str,
              oracle_noise: tuple[float, float]) -> tuple[object, tuple[str, ...], dict]:
    """(detector, its class names, its description for the outputs): the trained network in ``model``, or the
    ground-truth oracle of ``oracle_gt`` with ``oracle_noise`` (translation m, rotation deg RMS)."""
    if model is not None:
        from cadalign.models.maskrcnn.detector import load_pose_model  # lazy: pulls torch

        net, meta = load_pose_model(model, device)
        detector = det.TorchDetector(net, cfg.detector_score_thresh, device, cfg.tiles, cfg.nms_iou)
        return detector, tuple(meta.get("classes", class_names)), {"kind": "network", "run": str(model),
                                                                  "step": meta.get("step")}
    scene = det.resolve_scene_dir(oracle_gt)
    ocfg = oracle.OracleConfig(noise_t_m=oracle_noise[0], noise_r_deg=oracle_noise[1], seed=cfg.refine.seed)
    detector = oracle.OracleDetector(scene, ocfg)
    info = {"kind": "oracle", "note": "ground truth + noise, NOT a trained network", "scene": str(scene),
            "noise_t_m": oracle_noise[0], "noise_r_deg": oracle_noise[1]}
    console.print("[yellow]detector: ORACLE (ground-truth detections with noisy poses) - for tests and "
                  "demos of refinement/fusion only, not a trained network[/]")
    return detector, detector.classes.names, info


def _calibration(calib: Path | None, scene: Path | None) -> object:
    """The camera of ``--calib``, else that of the oracle's or the ground truth's BOP ``scene``."""
    # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.infer.run import calibration_from_scene, load_calibration

    if calib is not None:
        return load_calibration(calib)
    if scene is not None:
        return calibration_from_scene(scene)
    raise InputError("no camera intrinsics: pass --calib with the camera's calibration (a {\"K\": [...]} JSON, "
                     "OpenCV/ROS YAML, COLMAP cameras.txt, or a cameras.json from 'cadalign sfm')")


def _has_metric_poses(calib: Path) -> bool:
    from cadalign.infer.run import load_calibration  # lazy: pulls cv2; keeps `cadalign --help` light

    return bool(load_calibration(calib).T_world_from_cam_of)


def _track(source: Path, cad: Path, out: Path, model: Path | None, init_pose: Path | None, gt: Path | None,
           calib: Path | None, max_frames: int | None, cad_unit: str | None, device: str, preset: str,
           config: Path | None, overwrite: bool, topic: str | None, gt_poses: Path | None,
           nav: Path | None = None, stride: int = 1) -> None:
    """The tracker branch of ``infer`` (:mod:`cadalign.infer.track.run`)."""
    from cadalign.infer.track.config import PRESETS, TrackRunConfig  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.infer.track.run import read_init_pose, track_video  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.infer.track.truth import read_frame_poses  # lazy: pulls numpy; keeps `cadalign --help` light
    from cadalign.infer.video import iter_frames  # lazy: pulls cv2; keeps `cadalign --help` light
    from cadalign.sim.structure import load_structure  # lazy: pulls cv2; keeps `cadalign --help` light

    if model is None and init_pose is None and nav is None:
        raise InputError("the tracker needs a start: pass --init-pose FILE (a rough first-frame pose), --nav FILE "
                         "(rough poses per frame) and/or --model RUN (a trained detector); or give --oracle-gt "
                         "SIM_DIR (tests and demos) or --depth for the detector pipeline")
    cfg = resolve(TrackRunConfig, PRESETS, preset if preset in PRESETS else "balanced", config, {})
    restart = None
    info: dict = {"kind": "none"}
    network = None
    if model is not None:  # first: a wrong run folder fails before anything is read
        from cadalign.models.maskrcnn.detector import load_pose_model  # lazy: pulls torch

        net, meta = load_pose_model(model, device)
        network = (net, {**meta, "run": str(model)})
    structure = load_structure(cad, cad_unit)
    gt_scene = det.resolve_scene_dir(gt) if gt is not None else None
    first = next(iter(iter_frames(source, max_frames=1, topic=topic)), None)
    if first is None:
        raise InputError(f"{source} holds no readable frame")
    lens = None
    h, w = first.image.shape[:2]
    if calib is not None:
        from cadalign.formats.calibration import read_calibration  # lazy: pulls cv2; keeps `cadalign --help` light

        lens = read_calibration(calib)
        lens.check_size(w, h, f"{source}'s first frame {first.name}")
        camera = Camera(lens.K, w, h)
    elif gt_scene is not None:
        from cadalign.infer.run import calibration_from_scene  # lazy: pulls cv2; keeps `cadalign --help` light

        camera = Camera(calibration_from_scene(gt_scene, use_poses=False).K_default, w, h)
    else:
        raise InputError("no camera intrinsics: pass --calib calibration.json (your camera's calibration)")
    if model is not None:
        from cadalign.infer.track.start import detector_restarts  # lazy: pulls cv2; keeps `cadalign --help` light

        restart, info = detector_restarts(network, structure, camera, device)
    T0 = read_init_pose(init_pose, camera) if init_pose is not None else None
    navigation = read_frame_poses(nav, "navigation poses") if nav is not None else None
    path = track_video(cfg, source, structure, camera, out, init_pose=T0, restart_source=restart, gt_scene=gt_scene,
                       max_frames=max_frames, overwrite=overwrite, progress=track, lens=lens, topic=topic,
                       record={"detector": info, "cad": str(cad)}, nav=navigation, stride=stride)
    console.print(f"[green]poses written to {path}[/]")
    truth = read_frame_poses(gt_poses) if gt_poses is not None else _scene_camera_poses(gt_scene)
    if truth:
        from cadalign.infer.track.truth import ACCURATE, WRONG, truth_report  # lazy: pulls matplotlib

        summary = truth_report(out, structure, truth)
        if gt_poses is not None:  # (a simulation's parts are many: the counts below, not a line each)
            for name, v in summary["parts"].items():
                if v["median_mm"] is not None:
                    console.print(f"{name}: median {v['median_mm']:.1f} mm / {v['median_deg']:.2f} deg against "
                                  f"{gt_poses.name} ({summary['tracked']}/{summary['frames']} frames tracked)")
        console.print(f"of {summary['tracked']} tracked frames, {summary['accurate']} have every part within "
                      f"{ACCURATE[0]:.0f} mm / {ACCURATE[1]} deg and {summary['wrong']} one off by more than "
                      f"{WRONG[0]:.0f} mm or {WRONG[1]:.0f} deg ({out / 'truth_errors.png'})")
    _print_track_summary(out)


def _scene_camera_poses(scene: Path | None) -> dict:
    """``T_cam_from_world`` by frame name from a ``--gt`` BOP scene's ``cameras.json`` (a simulation's truth, a built
    dataset's poses) when it holds metric poses; else empty."""
    from cadalign.infer.run import load_calibration  # lazy: pulls cv2; keeps `cadalign --help` light

    if scene is None or not (scene / "cameras.json").is_file():
        return {}
    return {n: T.inverse() for n, T in load_calibration(scene / "cameras.json").T_world_from_cam_of.items()}


def _print_track_summary(out: Path) -> None:
    t = read_json(out / "timings.json")
    fps = t["frames_per_s"]
    console.print(f"{t['frames']} frames: {t['tracked']} tracked, {t['lost']} lost; "
                  f"{'n/a' if fps is None else f'{fps:.1f}'} frames/s (tracking, overlay apart)")
    if (out / "eval.json").is_file():
        rep = read_json(out / "eval.json")["fused"]
        o = rep["overall"]
        console.print(f"tracked: F1 {rep['detection']['f1']:.3f}  t_err mean {o['t_err_m']['mean']:.4f} m  "
                      f"R_err mean {o['r_err_deg']['mean']:.2f} deg")


def _print_summary(out: Path) -> None:
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

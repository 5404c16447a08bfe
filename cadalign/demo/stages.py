"""The demo's stages after the dataset build: train, infer, fuse, emulate (see :mod:`cadalign.demo.run`).

Each stage is a function ``(ctx) -> dict`` returning at least ``status`` ('done' or 'failed (...)'),
``dir`` (relative to the demo folder) and ``seconds``, plus the stage's headline numbers for the report.
Every stage's own ``run()`` reuses finished work, so a re-run of the demo skips what is already done.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cadalign.config import bounded, resolve
from cadalign.emulate import run as emulate_run
from cadalign.fuse.config import PRESETS, FuseConfig
from cadalign.fuse.run import run
from cadalign.infer import detect as det
from cadalign.infer.run import calibration_from_scene
from cadalign.infer.track.config import TrackRunConfig
from cadalign.infer.track.run import track_video
from cadalign.infer.track.start import detector_restarts
from cadalign.io import read_image, read_json
from cadalign.sim.navigation import first_fix
from cadalign.sim.structure import load_structure
from cadalign.types import Camera

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DemoConfig:
    """How much each learning stage of the demo does (the defaults fit the demo in ~10 min on 2 quiet cores)."""

    seg_steps: int = bounded(150, ge=1)
    """Training steps of the segmentation network ('fast' preset otherwise)."""
    depth_steps: int = bounded(300, ge=1)
    """Training steps of the depth network ('fast' preset otherwise)."""
    pose_steps: int = bounded(300, ge=1)
    """Training steps of the detector + pose head ('fast' preset otherwise)."""
    infer_frames: int = bounded(8, ge=1)
    """Held-out frames the pose inference runs on."""
    fuse_voxel_m: float = bounded(0.04, gt=0)
    """TSDF voxel size of the demo maps, metres."""
    lidar_preset: str = "hdl32"
    """LiDAR preset of the emulated scan."""


@dataclass(frozen=True)
class DemoContext:
    """Where the demo's inputs are: the simulation, the dataset to learn from and the demo folder."""

    out: Path
    sim_dir: Path
    scene: Path
    dataset: Path
    """A built dataset root (with splits.json) or, if the build failed, the simulator's BOP scene."""
    dataset_kind: str
    """'built' (from the video: SfM + alignment) or 'simulator ground truth' (the fallback)."""
    cfg: DemoConfig


def timed(name: str, fn: Callable[[DemoContext], dict], ctx: DemoContext) -> dict:
    """Run one stage; a failure is a result (status 'failed: ...'), logged with its traceback."""
    t0 = time.perf_counter()
    try:
        info = fn(ctx)
        info.setdefault("status", "done")
    except Exception as exc:  # the demo reports every stage; the summary's ok flag makes the command exit 1
        log.exception("demo stage %s failed", name)
        info = {"status": f"failed ({type(exc).__name__})", "error": str(exc)[:2000]}
    info["seconds"] = round(time.perf_counter() - t0, 2)
    return info


def _log_progress(name: str) -> Callable[[int, int, dict[str, float]], None]:
    """A training progress callback that logs about every tenth of the run (the demo has no bar per step)."""

    def report(step: int, total: int, metrics: dict[str, float]) -> None:
        if step == total or step % max(1, total // 10) == 0:
            log.info("%s: step %d/%d, loss %.4g", name, step, total, metrics.get("loss", float("nan")))

    return report


def _stop_if_interrupted(result: Any) -> Any:
    """A training run stopped by Ctrl-C/SIGTERM saved its checkpoint and returned: stop the demo too
    (re-running it resumes the training from that checkpoint)."""
    if getattr(result, "interrupted", False):
        raise KeyboardInterrupt(f"training interrupted at step {result.steps_done}; re-run the demo to resume")
    return result


def _with_steps(preset: Any, steps: int) -> Any:
    return dataclasses.replace(preset, loop=dataclasses.replace(preset.loop, steps=steps))


def train_seg_stage(ctx: DemoContext) -> dict:
    from cadalign.evaluate.dense import evaluate_seg  # lazy: pulls torch
    from cadalign.train.seg import PRESETS, train_seg  # lazy: pulls kornia, torch

    run = ctx.out / "train" / "seg"
    r = train_seg(_with_steps(PRESETS["fast"], ctx.cfg.seg_steps), ctx.dataset, run, resume=_has_ckpt(run),
                  progress=_log_progress("train seg"))
    _stop_if_interrupted(r)
    ev = evaluate_seg(run, ctx.dataset, run / "eval", split="test")
    return {"dir": "train/seg", "steps": r.steps_done, "final_loss": r.final_loss, "dataset": ctx.dataset_kind,
            "metrics": _pick(ev.metrics, ("miou", "pixel_accuracy", "iou")), "figures": _rel(ctx, ev.figures)}


def train_depth_stage(ctx: DemoContext) -> dict:
    from cadalign.evaluate.dense import evaluate_depth  # lazy: pulls torch
    from cadalign.train.depth import PRESETS, train_depth  # lazy: pulls kornia, torch

    run = ctx.out / "train" / "depth"
    r = train_depth(_with_steps(PRESETS["fast"], ctx.cfg.depth_steps), ctx.dataset, run, resume=_has_ckpt(run),
                    progress=_log_progress("train depth"))
    _stop_if_interrupted(r)
    ev = evaluate_depth(run, ctx.dataset, run / "eval", split="test")
    return {"dir": "train/depth", "steps": r.steps_done, "final_loss": r.final_loss, "dataset": ctx.dataset_kind,
            "metrics": ev.metrics, "figures": _rel(ctx, ev.figures)}


def train_pose_stage(ctx: DemoContext) -> dict:
    from cadalign.train.pose import PRESETS, run  # lazy: pulls kornia, torch

    out = ctx.out / "train" / "pose"
    r = run(_with_steps(PRESETS["fast"], ctx.cfg.pose_steps), ctx.dataset, out, resume=_has_ckpt(out),
            progress=_log_progress("train pose"))
    _stop_if_interrupted(r)
    score = out / "eval_heldout.json"
    return {"dir": "train/pose", "steps": r.steps_done, "final_loss": r.final_loss, "dataset": ctx.dataset_kind,
            "metrics": read_json(score) if score.is_file() else None}


def infer_stage(ctx: DemoContext) -> dict:
    """Part poses on the held-out (test) frames from RGB alone, evaluated against the truth: the structure tracker
    (:mod:`cadalign.infer.track`) with the camera's intrinsics only (no depth, no camera poses), started from a
    simulated navigation pose (the first frame's true pose turned 10 deg and moved 0.5 m, as a USBL/DVL fix is
    off) and restarted by the trained detector."""
    from cadalign.train.data import select  # lazy: pulls torch

    sel = select(ctx.dataset, "test")
    scene = sel.scene_dir
    names = {im_id: name for name, im_id in det.frame_ids(scene).items()}
    clip = ctx.out / "infer" / "heldout_frames"
    clip.mkdir(parents=True, exist_ok=True)
    picked = [names[im_id] for im_id in list(sel.ids)[: ctx.cfg.infer_frames]]
    for name in picked:
        link = clip / name
        if not link.exists():
            link.symlink_to((ctx.sim_dir / "frames" / name).resolve())
    structure = load_structure(ctx.scene)
    first = read_image(clip / sorted(picked)[0])
    K = calibration_from_scene(scene, use_poses=False).K_default
    camera = Camera(K, first.shape[1], first.shape[0])
    nav = first_fix(ctx.sim_dir, sorted(picked)[0])  # a navigation fix: truth turned 10 deg, moved 0.5 m
    restart, info = detector_restarts(ctx.out / "train" / "pose", structure, camera)
    out = ctx.out / "infer" / "poses"
    track_video(TrackRunConfig(), clip, structure, camera, out, init_pose=nav, restart_source=restart,
                gt_scene=scene, overwrite=True,
                record={"detector": info, "init_pose": "simulated navigation fix: truth + 10 deg / 0.5 m"})
    ev = out / "eval.json"
    return {"dir": "infer/poses", "frames": len(list(clip.iterdir())), "timings": read_json(out / "timings.json"),
            "eval": read_json(ev) if ev.is_file() else None,
            "inputs": "RGB frames + intrinsics; start: a simulated navigation fix (truth + 10 deg / 0.5 m) and the "
                      "trained detector; no depth, no camera poses"}


def fuse_stage(ctx: DemoContext) -> dict:
    """Semantic TSDF from the simulator's exact depth and labels, and from the trained networks' predictions."""

    cfg = resolve(FuseConfig, PRESETS, "default", overrides={"voxel_m": ctx.cfg.fuse_voxel_m})
    res: dict[str, Any] = {"dir": "fuse"}
    # no map checkpoint every 50 frames: the demo's maps take seconds to fuse but 0.3-0.4 GB to save (Ctrl-C
    # between frames still saves one; after a hard kill the map is fused again)
    once = {"checkpoint_every": 10**6}
    gt = run(cfg, ctx.sim_dir, ctx.out / "fuse" / "gt", depth="gt", labels="gt", **once)
    res["gt"] = read_json(gt / "fuse_report.json")
    seg, depth = ctx.out / "train" / "seg", ctx.out / "train" / "depth"
    if _has_ckpt(seg) and _has_ckpt(depth):
        pred = run(cfg, ctx.sim_dir, ctx.out / "fuse" / "pred", depth="pred", labels="pred", seg_model=seg,
                   depth_model=depth, **once)
        res["pred"] = read_json(pred / "fuse_report.json")
    return res


def emulate_stage(ctx: DemoContext) -> dict:
    """A LiDAR scan and a sonar image of the CAD scene from the ROV's first pose."""
    res: dict[str, Any] = {"dir": "emulate"}
    for sensor, preset in (("lidar", ctx.cfg.lidar_preset), ("sonar", None)):
        cls, presets, default = emulate_run.CONFIGS[sensor]
        cfg = resolve(cls, presets, preset or default)
        out = emulate_run.run(sensor, cfg, ctx.scene, ctx.out / "emulate" / sensor)
        res[sensor] = read_json(out / "emulate.json")
    return res


def _has_ckpt(run: Path) -> bool:
    return (Path(run) / "checkpoints" / "last.pt").is_file()


def _pick(d: dict, keys: tuple[str, ...]) -> dict:
    return {k: v for k, v in d.items() if any(k == p or k.startswith(p) for p in keys)} or d


def _rel(ctx: DemoContext, paths: Any) -> list[str]:
    return [str(Path(p).resolve().relative_to(ctx.out.resolve())) for p in paths or ()]

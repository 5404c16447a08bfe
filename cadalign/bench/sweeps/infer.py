"""The ``infer`` sweep: what each refinement setting costs per frame on top of the detector alone.

Every setting runs the whole ``cadalign infer`` path (:func:`cadalign.infer.run.run`: detector, CAD model
identification, refinement, temporal fusion; no overlay video) over the same frames, from a fresh output
folder each repeat, and is scored against the simulator's truth (``eval.json`` of the run). The baseline,
``detector only`` (preset ``none``: the network's poses, no refinement, no fusion), is one of the settings,
so every setting's cost is also reported as a ratio to it measured in the same run (``cost_ratio``, see
:func:`cadalign.bench.registry.summarise_stage`).

What runs:

- with a :class:`InferSource` (``cadalign bench infer --model RUN ...``): the user's trained network on the
  user's frames (a simulation, or a built dataset's frames with the simulation as ``--gt``);
- without one (``bench all``, the tests): a small network trained for the size's step budget on the bench
  clip's training block (``prepare``-like setup, not timed) and the clip's frames. Such a network detects
  little, so the refinement costs are a lower bound there; the detector's cost is the real one.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cadalign.bench.data import BenchData
from cadalign.bench.framework import BenchConfig, Metric, Sweep, SweepPoint
from cadalign.config import merge_mappings, resolve
from cadalign.infer.config import PRESETS, InferConfig
from cadalign.infer.detect import TorchDetector, resolve_scene_dir
from cadalign.infer.run import calibration_from_scene, run
from cadalign.io import fingerprint, read_json
from cadalign.sim.structure import load_structure

BASELINE = "detector only"
NO_REUSE: dict[str, Any] = {"reuse_box_iou": 0.0, "track_init": "off"}
"""Every detection identified and refined from the network's pose (no model or pose taken from a track)."""

INFER_POINTS: dict[int, tuple[tuple[str, str, dict[str, Any]], ...]] = {
    0: ((BASELINE, "none", {}), ("fast", "fast", {}), ("balanced", "balanced", {})),
    1: ((BASELINE, "none", {}), ("fast", "fast", {}), ("fast, no model reuse", "fast", NO_REUSE),
        ("balanced", "balanced", {})),
    2: ((BASELINE, "none", {}), ("fast", "fast", {}), ("fast, no model reuse", "fast", NO_REUSE),
        ("balanced", "balanced", {}), ("balanced, 4 yaw restarts", "balanced", {"refine": {"yaw_hypotheses": 4}}),
        ("accurate", "accurate", {})),
}
"""(name, infer preset, overrides) per size level; the first is the baseline."""


@dataclass(frozen=True)
class InferSource:
    """A trained network and the frames to time it on (``cadalign bench infer --model``)."""

    model: Path
    """``cadalign train pose`` run folder."""
    frames: Path
    """Video or folder of frames."""
    gt: Path
    """Simulation folder or BOP scene holding the frames' truth (and intrinsics, camera poses)."""
    cad: Path
    """Scene spec (parts and classes) the network was trained on."""
    depth: Path | None = None
    """Simulation folder or BOP scene with depth for ICP (None: silhouette refinement only)."""
    overrides: dict[str, Any] = field(default_factory=dict)
    """InferConfig keys applied to every setting (e.g. ``enhance = "none"`` for already enhanced frames)."""
    max_frames: int | None = None
    """Time at most this many frames."""


def run_folder_name(preset: str, overrides: dict[str, Any]) -> str:
    """The folder of one infer setting: the preset and a hash of its override values (two settings with the same
    override keys but other values must not share a folder)."""
    return preset + (f"_{fingerprint(overrides)[:8]}" if overrides else "")


def _train_small(data: BenchData, cfg: BenchConfig) -> Path:
    """A small pose network trained on the bench clip for the size's step budget (reused when finished)."""

    from cadalign.train.loop import LoopConfig  # lazy: pulls torch
    from cadalign.train.pose import PRESETS, run  # lazy: pulls kornia, torch

    clip = data.clip()
    w, h = data.size.clip_resolution
    out = data.work("infer", f"pose_{w}x{h}_{data.size.train_steps}")
    if not (out / "train_config.json").is_file() or not any((out / "checkpoints").glob("*.pt")):
        shutil.rmtree(out)  # a leftover is from an interrupted training
        n = data.size.train_steps
        base = PRESETS["fast"]
        tcfg = dataclasses.replace(base, model=dataclasses.replace(base.model, input_hw=(h, w)),
                                   loop=LoopConfig(steps=n, batch_size=2, lr=1e-3, checkpoint_every=n,
                                                   log_every=max(1, n // 5), seed=cfg.seed))
        run(tcfg, clip / "gt" / "sim" / "000000", out)
    return out


def infer_sweep(data: BenchData, cfg: BenchConfig, source: InferSource | None = None) -> Sweep:
    """Infer presets (detector only, fast, balanced, ...): ADD(-S) recall vs ms per frame, ratio to the detector."""

    def setup() -> dict[str, Any]:
        from cadalign.models.maskrcnn.detector import load_pose_model  # lazy: pulls torch

        if source is None:
            run_dir, clip = _train_small(data, cfg), data.clip()
            src = InferSource(run_dir, clip / "frames", clip, data.scene(), clip)
        else:
            src = source
        gt = resolve_scene_dir(src.gt)
        net, meta = load_pose_model(src.model)
        structure = load_structure(src.cad)
        return {"src": src, "gt": gt, "depth": resolve_scene_dir(src.depth) if src.depth is not None else None,
                "net": net, "info": {"kind": "network", "run": str(src.model), "step": meta.get("step")},
                "classes": tuple(meta.get("classes", structure.class_names)), "models": structure.models,
                "calib": calibration_from_scene(gt)}

    def measure(s: dict[str, Any], knobs: dict[str, Any], _: Any) -> dict[str, float]:
        import torch  # lazy: heavy dependency (torch)

        src: InferSource = s["src"]
        overrides = merge_mappings(merge_mappings({"overlay": False}, src.overrides), knobs["overrides"])
        icfg = resolve(InferConfig, PRESETS, knobs["preset"], overrides=overrides)
        out = data.work("infer", "runs", run_folder_name(knobs["preset"], knobs["overrides"]))
        shutil.rmtree(out)  # every repeat runs from scratch (run() would reuse a finished folder)
        detector = TorchDetector(s["net"], icfg.detector_score_thresh, tiles=icfg.tiles, nms_iou=icfg.nms_iou)
        t0 = time.perf_counter()
        run(icfg, src.frames, detector, s["models"], s["classes"], out, calib=s["calib"], detector_info=s["info"],
            depth_scene=s["depth"], gt_scene=s["gt"], max_frames=src.max_frames)
        wall = time.perf_counter() - t0
        t, ev = read_json(out / "timings.json"), read_json(out / "eval.json")["fused"]
        res = {"ms_per_frame": t["pipeline_ms_per_frame"] or 0.0, "frames": float(t["frames"]),
               "poses": float(t["poses"]), "frames_per_s": t["pipeline_fps"] or float("nan"),
               "run_s": wall, "torch_threads": float(torch.get_num_threads()),
               "ms_detector": t["stages_ms"]["detector"], "ms_pose": t["stages_ms"]["pose"],
               "ms_refinement": t["stages_ms"]["refinement"],
               "f1": ev["detection"]["f1"], "add_s_01d": ev["overall"]["add_s_01d"],
               "t_err_m": ev["overall"]["t_err_m"]["mean"], "r_err_deg": ev["overall"]["r_err_deg"]["mean"]}
        for name, c in ev["per_class"].items():
            res[f"{name}.r_err_deg"] = c["r_err_deg"]["mean"]
            res[f"{name}.t_err_m"] = c["t_err_m"]["mean"]
            res[f"{name}.f1"] = c["detection"]["f1"]
        return res

    # a user's network and frames are part of a setting's identity: another --model in the same folder re-runs
    extra = {} if source is None else {"source": fingerprint({k: str(v) for k, v in source.__dict__.items()})[:10]}
    pts = tuple(SweepPoint(n, {"preset": p, "overrides": o, **extra}) for n, p, o in INFER_POINTS[data.size.level])
    where = ("the user's network (--model) on the given frames" if source is not None else
             f"a {data.size.train_steps}-step network trained on the bench clip's training block, on the clip's "
             f"{data.size.clip_frames} frames at {data.size.clip_resolution[0]}x{data.size.clip_resolution[1]} "
             "(it detects little: refinement costs are a lower bound)")
    return Sweep(
        "infer", pts, Metric("add_s_01d", "ADD(-S) < 0.1 d recall of the reported poses", True),
        Metric("ms_per_frame", "ms per frame (detector + identification + refinement + fusion, wall)"),
        measure, setup, baseline=BASELINE,
        description=(f"The whole infer pipeline per preset ({where}), no overlay, from scratch each repeat. Cost: "
                     "wall ms per frame of the pipeline; cost_ratio: that over the detector-only setting measured "
                     "in the same run. Per-stage ms (detector, pose head + identification, refinement), "
                     "frames/s, F1 and per-class errors are in the record. Accuracy: the share of visible "
                     "targets whose fused pose is within 10% of the part's diameter (ADD, ADD-S for symmetric "
                     "parts)."))


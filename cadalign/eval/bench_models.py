"""Sweeps of SfM, the dense networks (segmentation, depth) and pose refinement.

SfM runs on the size's SfM clip and is scored against the simulator's exact cameras
(:mod:`cadalign.eval.sfm_metrics`). Each network setting trains a small model for the size's step budget
(``prepare``, not timed: the benchmark asks what an input resolution / width costs at inference) and is
scored on the clip's held-out time blocks. Refinement uses :func:`cadalign.infer.bench.refine_sweep`.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.eval.bench_data import BenchData
from cadalign.eval.bench_framework import BenchConfig, Metric, Sweep, SweepPoint
from cadalign.io import fingerprint

SCENE = Path("gt") / "sim" / "000000"

_NO_REFINE = ("balanced, no refinement", {"mapper": {"refine_iterations": 0}})
_GLOBAL = ("balanced, global mapper", {"mapper": {"kind": "global"}})
SFM_PLAIN = "plain pycolmap"
"""Name of the sfm sweep's baseline setting: pycolmap's SIFT, sequential matching and incremental mapping with its
defaults (:mod:`cadalign.sfm.plain`), on the same frames in the same run."""
SFM_POINTS = {
    0: ((SFM_PLAIN, {}), ("fast", {}), ("balanced", {}), ("accurate", {})),
    1: ((SFM_PLAIN, {}), ("fast", {}), ("balanced", {}), ("accurate", {}), _NO_REFINE, _GLOBAL),
    2: ((SFM_PLAIN, {}), ("fast", {}), ("balanced", {}), ("accurate", {}), _NO_REFINE, _GLOBAL,
        ("balanced, exhaustive", {"matching": {"pairing": "exhaustive"}})),
}
"""Plain pycolmap (the baseline), presets and one-knob variants (features: the presets' SIFT budgets; matcher:
pairing; mapper: kind and refinement)."""


def _preset_of(name: str) -> str:
    return name.split(",")[0]


def sfm_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """SfM presets and feature/matcher/mapper variants: rotation error vs seconds, on the simulated SfM clip."""

    def measure(sim: Path, knobs: dict[str, Any], _: Any) -> dict[str, float]:
        from cadalign.config import resolve
        from cadalign.eval.sfm_metrics import evaluate
        from cadalign.sfm import PRESETS, SfMConfig, run

        if knobs["preset"] == SFM_PLAIN:
            return plain_measure(sim, data.work("sfm", fingerprint(knobs)), cfg.seed)
        c = resolve(SfMConfig, PRESETS, knobs["preset"], overrides={**knobs["overrides"], "num_threads": 1,
                                                                     "seed": cfg.seed})
        out = data.work("sfm", fingerprint(knobs))
        t0 = time.perf_counter()
        run(c, sim / "frames", out, overwrite=True)
        sec = time.perf_counter() - t0
        g = evaluate(out, sim)
        return {"sfm_s": sec, "rot_err_deg": g["rot_err_deg_mean"], "centre_rmse_m": g["centre_rmse_m"],
                "centre_rmse_rel": g["centre_rmse_rel"], "registration_rate": g["registration_rate"],
                "rel_rot_err_deg": g["rel_rot_err_deg_mean"]}

    w, h = data.size.sfm_resolution
    pts = tuple(SweepPoint(n, {"preset": _preset_of(n), "overrides": o}) for n, o in SFM_POINTS[data.size.level])
    return Sweep(
        "sfm", pts, Metric("rel_rot_err_deg", "relative rotation error of consecutive frames, mean (deg)"),
        Metric("sfm_s", "seconds per SfM run (1 thread)"), measure, data.sfm_clip, baseline=SFM_PLAIN,
        description=(f"SfM (pycolmap, 1 thread) on {data.size.sfm_frames} simulated frames at {w}x{h} of the default "
                     f"scene, presets and single-knob variants, against the simulator's exact cameras; '{SFM_PLAIN}' "
                     "(SIFT, sequential matching, incremental mapping, pycolmap's defaults, one shared camera) runs "
                     "on the same frames in the same run, and the cost ratio divides each setting's seconds by its "
                     "seconds. Accuracy: "
                     "the gauge-free rotation error between consecutive frames (the absolute rotation error after "
                     "a Sim(3) fit of the centres, rot_err_deg, is in the record: on a short arc the fit cannot pin "
                     "the roll about the path and that error mostly measures the gauge), with centre RMSE and "
                     "registration rate."),
        repeats=1 if data.size.level < 2 else 2)  # 1 thread + fixed seed: repeats only re-measure the time


def plain_measure(sim: Path, work: Path, seed: int) -> dict[str, float]:
    """Plain pycolmap (:func:`cadalign.sfm.plain.run_plain`, 1 thread) on ``sim``'s frames, scored like the presets.

    Raises:
        DegenerateGeometryError: plain pycolmap found no model (the setting is then recorded as failed).
    """
    from cadalign.errors import DegenerateGeometryError
    from cadalign.eval.sfm_metrics import GT_SCENE, pose_errors
    from cadalign.io import read_json
    from cadalign.sfm.plain import run_plain
    from cadalign.sfm.report import cameras_json

    res = run_plain(sim / "frames", work, num_threads=1, seed=seed)
    if res.model is None:
        raise DegenerateGeometryError(f"plain pycolmap found no model in {res.frames} frames")
    gt = read_json(sim / GT_SCENE / "cameras.json")
    pe = pose_errors(cameras_json(res.model), gt)
    rmse = float(np.sqrt(np.mean(pe.centre_err_m**2)))
    return {"sfm_s": res.seconds["total"], "rot_err_deg": float(pe.rot_err_deg.mean()), "centre_rmse_m": rmse,
            "registration_rate": len(pe.names) / len(gt["frames"]),
            "rel_rot_err_deg": float(pe.rel_rot_err_deg.mean()),
            **{f"{k}_s": v for k, v in res.seconds.items() if k != "total"}}


# ---- dense networks ------------------------------------------------------------------------------------

NET_POINTS = {0: ((0.25, 4), (0.5, 4), (0.5, 8)),
              1: ((0.25, 8), (0.5, 8), (0.5, 16), (1.0, 8)),
              2: ((0.25, 12), (0.5, 12), (0.5, 24), (1.0, 12))}


def _loop(data: BenchData, cfg: BenchConfig):  # -> LoopConfig
    from cadalign.train.loop import LoopConfig

    n = data.size.train_steps
    return LoopConfig(steps=n, batch_size=2, lr=3e-3, checkpoint_every=n, log_every=max(1, n // 5), seed=cfg.seed)


def held_out_ids(scene: Path) -> tuple[int, ...]:
    """The image ids of ``scene`` not in its training split: val + test (training here never validates),
    or every frame when the scene is too short to have either."""
    from cadalign.errors import InputError
    from cadalign.train.data import select

    ids: list[int] = []
    for split in ("val", "test"):
        try:
            ids += select(scene, split).ids
        except InputError:
            pass
    return tuple(sorted(ids)) or select(scene, "all").ids


def _train(task: str, data: BenchData, cfg: BenchConfig, knobs: dict[str, Any]) -> tuple[Path, float]:
    """Train one small network of ``task`` with ``knobs`` (scale, width) into a fresh run folder."""
    scene = data.clip() / SCENE
    out = data.work(task, f"s{knobs['scale']:g}_w{knobs['width']}")
    shutil.rmtree(out)  # a leftover is from an interrupted run of this setting
    t0 = time.perf_counter()
    if task == "seg":
        from cadalign.models.resunet import ResUNetConfig
        from cadalign.train.seg import SegTrainConfig, train_seg

        train_seg(SegTrainConfig(model=ResUNetConfig(base_channels=knobs["width"]), scale=knobs["scale"],
                                 loop=_loop(data, cfg)), scene, out, val_split=None)
    else:
        from cadalign.models.dispnet import DispNetConfig
        from cadalign.train.depth import DepthTrainConfig, train_depth

        train_depth(DepthTrainConfig(model=DispNetConfig(base_channels=knobs["width"]), scale=knobs["scale"],
                                     loop=_loop(data, cfg)), scene, out)
    return out, time.perf_counter() - t0


def score_net(task: str, scene: Path, run: Path, train_s: float = float("nan"),
              split: str | None = None) -> dict[str, float]:
    """Score the network of training run ``run`` on the frames of ``split`` of the BOP ``scene`` (default:
    :func:`held_out_ids`): mIoU (seg) or delta1/AbsRel (depth), and the
    median over frames of the inference ms (each the faster of two passes)."""
    import torch

    from cadalign.data.torch_datasets import DepthDataset, SegmentationDataset
    from cadalign.eval.depth_metrics import DepthAccumulator, DepthEvalConfig, frame_depth_errors
    from cadalign.eval.seg_metrics import confusion_matrix, seg_metrics
    from cadalign.infer.dense import load_dense_model, metric_depth, seg_probabilities
    from cadalign.train.data import select

    ids = select(scene, split).ids if split else held_out_ids(scene)
    ds = (SegmentationDataset if task == "seg" else DepthDataset)(scene, ids)
    dm = load_dense_model(run, task=task)
    ms, cm, acc = [], np.zeros((len(dm.classes), len(dm.classes)), np.int64), DepthAccumulator()
    with torch.inference_mode():
        for i in range(len(ds)):
            item = ds[i]
            best = np.inf  # the faster of two passes: load on a shared machine only ever adds time
            for _ in range(2):
                t0 = time.perf_counter()
                out = seg_probabilities(dm, item["image"]) if task == "seg" else metric_depth(dm, item["image"])
                best = min(best, 1000 * (time.perf_counter() - t0))
            ms.append(best)
            if task == "seg":
                cm += confusion_matrix(out[0].argmax(0).numpy(), item["label"].numpy(), len(dm.classes))
            else:
                acc.add(*frame_depth_errors(out[0].numpy().astype(np.float64),
                                            item["depth"][0].numpy().astype(np.float64), DepthEvalConfig()))
    res = {"ms_per_frame": float(np.median(ms)), "train_s": train_s, "frames": float(len(ds))}
    if task == "seg":
        m = seg_metrics(cm, dm.classes)
        res.update(miou=m.miou, miou_fg=m.miou_fg, pixel_accuracy=m.pixel_accuracy)
    else:
        s = acc.summary()
        res.update(delta1=float(s["delta1"]), abs_rel=float(s["abs_rel"]))
    return res


def _net_sweep(task: str, data: BenchData, cfg: BenchConfig) -> Sweep:
    w, h = data.size.clip_resolution
    acc = Metric("miou", "mIoU on held-out frames", True) if task == "seg" else \
        Metric("delta1", "delta1 (share within 25%) on held-out frames", True)
    model = "ResUNet" if task == "seg" else "DispNet"
    return Sweep(
        task, tuple(SweepPoint(f"x{s:g} w{c}", {"scale": s, "width": c}) for s, c in NET_POINTS[data.size.level]),
        acc, Metric("ms_per_frame", "ms per frame (inference, CPU)"),
        lambda _s, _k, prep: score_net(task, data.clip() / SCENE, *prep), data.clip,
        prepare=lambda _s, k: _train(task, data, cfg, k),
        description=(f"{model} trained for {data.size.train_steps} steps (batch 2) per setting on the clip's training "
                     f"time blocks ({data.size.clip_frames} frames at {w}x{h}, all water effects), scored on the "
                     "held-out (val + test) blocks at full resolution. Knobs: input scale (x) and base width (w). "
                     "Training time is in the record (train_s), not on the axis. Short training: the accuracy ranks "
                     "settings at a fixed budget, it is not what a full training reaches."))


def seg_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """ResUNet input scale x width: mIoU vs ms per frame."""
    return _net_sweep("seg", data, cfg)


def depth_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """DispNet input scale x width: delta1 vs ms per frame."""
    return _net_sweep("depth", data, cfg)


# ---- pose refinement -----------------------------------------------------------------------------------

REFINE_ITERS = {0: (0, 1, 3), 1: (0, 1, 2, 5, 10), 2: (0, 1, 2, 3, 5, 10, 20)}


def refine_sweep(data: BenchData, cfg: BenchConfig) -> Sweep:
    """Silhouette + depth refinement iterations from oracle-noisy poses: ADD vs ms per instance."""
    max_frames = (4, 8, 16)[data.size.level]

    def setup() -> dict[str, Any]:
        from cadalign.build_dataset import load_structure

        return {"scene": data.sfm_clip() / SCENE, "models": load_structure(data.scene()).models}

    def measure(s: dict[str, Any], knobs: dict[str, Any], _: Any) -> dict[str, float]:
        from cadalign.infer.bench import refine_sweep as sweep
        from cadalign.infer.refine import RefineConfig

        rows = sweep(s["scene"], s["models"], iters=(knobs["iters"],), cfg=RefineConfig(seed=cfg.seed),
                     max_frames=max_frames)
        r = next(r for r in rows if r.method == knobs["method"])
        return {"add_m": r.add_m, "r_err_deg": r.r_err_deg, "t_err_m": r.t_err_m, "ms_per_instance": r.ms,
                "instances": float(r.n), "eligible": float(r.n_eligible), "mean_iters": r.mean_iters}

    return Sweep(
        "refine", tuple(SweepPoint(f"{n} it", {"iters": n, "method": "both"}) for n in REFINE_ITERS[data.size.level]),
        Metric("add_m", "ADD pose error, mean (m)"), Metric("ms_per_instance", "ms per instance"), measure, setup,
        description=(f"Pose refinement (silhouette then depth ICP) of valves and hot stabs from the oracle "
                     f"detector's noisy poses with true masks, first {max_frames} frames of the SfM clip (the default "
                     "refinement skips masks under 400 px, so the small clip would refine nothing); ADD over all "
                     "instances, refined or not. The iteration budget is the knob (infer.bench.refine_sweep; it "
                     "averages over instances, so one repeat)."),
        repeats=1)

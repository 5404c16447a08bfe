"""The dense networks' sweeps (segmentation, depth): each setting trains a small model for the size's step budget
(``prepare``, not timed: the benchmark asks what an input resolution / width costs at inference) and is scored on
the clip's held-out time blocks.
"""
from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.bench.data import BenchData
from cadalign.bench.framework import BenchConfig, Metric, Sweep, SweepPoint
from cadalign.errors import InputError
from cadalign.metrics.depth import DepthAccumulator, DepthEvalConfig, frame_depth_errors
from cadalign.metrics.seg import confusion_matrix, seg_metrics

NET_POINTS = {0: ((0.25, 4), (0.5, 4), (0.5, 8)),
              1: ((0.25, 8), (0.5, 8), (0.5, 16), (1.0, 8)),
              2: ((0.25, 12), (0.5, 12), (0.5, 24), (1.0, 12))}


SCENE = Path("gt") / "sim" / "000000"


def _loop(data: BenchData, cfg: BenchConfig):  # -> LoopConfig
    from cadalign.train.loop import LoopConfig  # lazy: pulls torch

    n = data.size.train_steps
    return LoopConfig(steps=n, batch_size=2, lr=3e-3, checkpoint_every=n, log_every=max(1, n // 5), seed=cfg.seed)


def held_out_ids(scene: Path) -> tuple[int, ...]:
    """The image ids of ``scene`` not in its training split: val + test (training here never validates),
    or every frame when the scene is too short to have either."""
    from cadalign.train.data import select  # lazy: pulls torch

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
        from cadalign.models.resunet import ResUNetConfig  # lazy: pulls torch
        from cadalign.train.seg import SegTrainConfig, train_seg  # lazy: pulls kornia, torch

        train_seg(SegTrainConfig(model=ResUNetConfig(base_channels=knobs["width"]), scale=knobs["scale"],
                                 loop=_loop(data, cfg)), scene, out, val_split=None)
    else:
        from cadalign.models.dispnet import DispNetConfig  # lazy: pulls torch
        from cadalign.train.depth import DepthTrainConfig, train_depth  # lazy: pulls kornia, torch

        train_depth(DepthTrainConfig(model=DispNetConfig(base_channels=knobs["width"]), scale=knobs["scale"],
                                     loop=_loop(data, cfg)), scene, out)
    return out, time.perf_counter() - t0


def score_net(task: str, scene: Path, run: Path, train_s: float = float("nan"),
              split: str | None = None) -> dict[str, float]:
    """Score the network of training run ``run`` on the frames of ``split`` of the BOP ``scene`` (default:
    :func:`held_out_ids`): mIoU (seg) or delta1/AbsRel (depth), and the
    median over frames of the inference ms (each the faster of two passes)."""
    import torch  # lazy: heavy dependency (torch)

    from cadalign.infer.dense import load_dense_model, metric_depth, seg_probabilities  # lazy: pulls torch
    from cadalign.train.data import select  # lazy: pulls torch
    from cadalign.train.datasets import DepthDataset, SegmentationDataset  # lazy: pulls torch

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

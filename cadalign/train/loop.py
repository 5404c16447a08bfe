"""The shared training loop (segmentation, depth, detection + pose).

``train_loop(model, step_fn, dataset, cfg, run_dir)`` runs ``cfg.steps`` optimiser steps of AdamW with a
cosine schedule after a linear warm-up. Batches come from an infinite, seeded sample stream: the
concatenation of per-epoch permutations that depend only on ``(seed, epoch)``; step ``s`` takes stream
positions ``[s*B, (s+1)*B)``, so the sampler position is the step count and a resumed run replays exactly
the batches of an uninterrupted one. Augmentation gets a ``torch.Generator`` seeded from ``(seed, step)``.

Files in ``run_dir``: ``checkpoints/last.pt`` (+ ``step_XXXXXX.pt`` every ``checkpoint_every``; also on
SIGINT/SIGTERM and at the end), ``metrics.json`` (``{"rows": [{"step", "loss", "loss_avg", <step_fn
metrics>, "lr", "seconds", "cpu_seconds", <val metrics>}...]}``) and ``loss.png``. Under ``torchrun`` (``RANK`` and
``WORLD_SIZE`` set) the model is wrapped in DistributedDataParallel (gloo on CPU), each rank takes its
slice of the global batch, and only rank 0 writes files.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import DataLoader, Dataset, default_collate

from cadalign.config import bounded, config_differences, to_dict
from cadalign.errors import ConfigError, TrainingError
from cadalign.io import read_json, stop_on_signals, write_json
from cadalign.train.batches import StepBatchSampler, check_finite_batch, sample_names, stream_indices
from cadalign.train.checkpoint import (
    LAST,
    check_extra_state,
    load_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
    unwrap,
)
from cadalign.train.devices import any_rank, bf16_native, dist_setup, is_main_rank, rank_device, to_device
from cadalign.train.plots import plot_metrics

log = logging.getLogger(__name__)

__all__ = ["LoopConfig", "StepFn", "TrainResult", "augment_seed", "check_finite_batch", "is_main_rank",
           "rank_device", "stream_indices", "train_loop"]


@dataclass(frozen=True)
class LoopConfig:
    steps: int = bounded(200, ge=1)
    """Optimiser steps in total."""
    batch_size: int = bounded(4, ge=1)
    """Global batch size (split across DDP ranks)."""
    lr: float = bounded(1e-3, gt=0)
    """Peak learning rate (AdamW)."""
    weight_decay: float = bounded(1e-4, ge=0)
    """AdamW weight decay."""
    grad_clip: float = bounded(10.0, ge=0)
    """Gradient norm clip; 0 = off."""
    checkpoint_every: int = bounded(50, ge=1)
    """Steps between checkpoints; one is also written on KeyboardInterrupt/SIGTERM and at the end."""
    keep_checkpoints: int = bounded(5, ge=0)
    """Numbered checkpoints kept (the newest; ``last.pt`` always), 0 = all. A 6600-step pose run kept all 66 of
    its 58 MB checkpoints (3.8 GB) and filled a disk."""
    log_every: int = bounded(10, ge=1)
    """Steps between metric rows in metrics.json."""
    seed: int = 0
    """Seed of model-independent randomness: sample order, augmentation, dropout."""
    amp: bool = False
    """Autocast (bf16) where the device computes bf16 natively (:func:`bf16_native`: a GPU with bf16, a CPU with
    AVX512-BF16 or AMX); elsewhere the run stays in fp32, since emulated bf16 is slower than fp32."""
    num_workers: int = bounded(0, ge=0)
    """DataLoader worker processes (0 = load in the main process)."""
    warmup: float = bounded(0.05, ge=0, lt=1)
    """Fraction of the steps with a linear learning-rate warm-up before the cosine decay."""


# Fields that may change between a run and its resumption (they do not change the optimisation).
RESUMABLE_CHANGES = {"steps", "checkpoint_every", "keep_checkpoints", "log_every", "num_workers"}


class StepFn(Protocol):
    def __call__(self, model: nn.Module, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        """Return the scalar loss of ``batch`` and named float metrics for logging."""
        ...


@dataclass(frozen=True)
class TrainResult:
    run_dir: Path
    """The run folder (checkpoints/, metrics.json, loss.png)."""
    steps_done: int
    """Optimiser steps completed (including those of a resumed run)."""
    final_loss: float
    """Loss of the last step run (nan when no step ran)."""
    seconds: float
    """Wall time of this call."""
    interrupted: bool
    """True when stopped by KeyboardInterrupt/SIGTERM (a checkpoint was written)."""


def augment_seed(seed: int, step: int, rank: int) -> int:
    """Seed of the augmentation generator of ``step`` on DDP ``rank``: each rank augments its own slice of the
    batch, so the ranks must draw differently (rank 0 keeps the single-process seed)."""
    return seed * 7_919 + step * 104_729 + 1 + rank * 15_485_863


def _lr_lambda(cfg: LoopConfig) -> Callable[[int], float]:
    warm = int(round(cfg.warmup * cfg.steps))

    def f(step: int) -> float:
        if step < warm:
            return (step + 1) / warm
        t = (step - warm) / max(cfg.steps - warm, 1)
        return 0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(t, 1.0)))

    return f


class _Run:
    """Mutable state of one train_loop call (kept out of the public function for size)."""

    def __init__(self, model: nn.Module, cfg: LoopConfig, run_dir: Path, extra_state: dict | None,
                 rank: int) -> None:
        self.model, self.cfg, self.run_dir, self.extra, self.rank = model, cfg, Path(run_dir), extra_state, rank
        params = [p for p in model.parameters() if p.requires_grad]
        # the fused kernel: one pass over all parameters (41 -> 8 ms a step for the fast detector's 5 M
        # parameters on one core); where it cannot run (another device, non-float parameters), the default
        fused = bool(params) and all(p.device.type in ("cpu", "cuda") and p.is_floating_point() for p in params)
        self.opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay, fused=fused or None)
        self.sched = torch.optim.lr_scheduler.LambdaLR(self.opt, _lr_lambda(cfg))
        self.step = 0
        self.rows: list[dict[str, float]] = []
        self.window: list[float] = []
        self.seconds0 = 0.0
        self.cpu0 = 0.0
        self.t0 = time.perf_counter()
        self.c0 = time.process_time()
        self.bf16 = False  # whether the steps autocast (LoopConfig.amp on a device with native bf16)

    def seconds(self) -> float:
        """Wall-clock training seconds over this run and the runs it resumed."""
        return self.seconds0 + time.perf_counter() - self.t0

    def cpu_seconds(self) -> float:
        """CPU seconds of this process (all threads) over this run and the runs it resumed."""
        return self.cpu0 + time.process_time() - self.c0

    @property
    def ckpt_dir(self) -> Path:
        return self.run_dir / "checkpoints"

    def state(self) -> dict[str, Any]:
        return {
            "model": unwrap(self.model).state_dict(), "optimizer": self.opt.state_dict(),
            "scheduler": self.sched.state_dict(), "step": self.step, "sampler_position": self.step,
            "rng": rng_state(), "extra_state": to_dict(self.extra or {}), "loop_config": to_dict(self.cfg),
            "window": list(self.window), "seconds": self.seconds(), "cpu_seconds": self.cpu_seconds(),
        }

    def save(self, *, numbered: bool) -> None:
        if self.rank != 0:
            return
        state = self.state()
        if numbered:
            save_checkpoint(self.ckpt_dir / f"step_{self.step:06d}.pt", state)
        save_checkpoint(self.ckpt_dir / LAST, state)
        if numbered and self.cfg.keep_checkpoints:  # after last.pt is safe: a kill never leaves fewer than kept
            for old in sorted(self.ckpt_dir.glob("step_*.pt"))[:-self.cfg.keep_checkpoints]:
                old.unlink(missing_ok=True)

    def restore(self, path: Path, device: torch.device) -> None:
        ck = load_checkpoint(path, map_location=device)
        check_extra_state(ck.get("extra_state"), self.extra, path)
        old = ck.get("loop_config", {})
        now = to_dict(self.cfg)
        diff = [k for k in config_differences(old, self.cfg) if k not in RESUMABLE_CHANGES]
        if diff:
            changes = ", ".join(f"{k}: {old.get(k, '<missing>')!r} -> {now.get(k, '<removed>')!r}" for k in diff)
            raise ConfigError(
                f"{path} was trained with other loop settings ({changes}); "
                "resume with the same settings or use a new --out folder"
            )
        unwrap(self.model).load_state_dict(ck["model"])
        self.opt.load_state_dict(ck["optimizer"])
        self.sched.load_state_dict(ck["scheduler"])
        self.sched.lr_lambdas[0] = _lr_lambda(self.cfg)  # a longer --steps re-stretches the schedule
        self.step = int(ck["step"])
        self.window = list(ck.get("window", []))
        self.seconds0 = float(ck.get("seconds", 0.0))
        self.cpu0 = float(ck.get("cpu_seconds", 0.0))
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        set_rng_state(ck["rng"])
        mpath = self.run_dir / "metrics.json"
        if mpath.is_file():
            self.rows = [r for r in read_json(mpath).get("rows", []) if r["step"] <= self.step]
        log.info("resumed %s at step %d", path, self.step)

    def write_metrics(self, *, plot: bool) -> None:
        if self.rank != 0:
            return
        write_json(self.run_dir / "metrics.json", {"loop_config": to_dict(self.cfg), "bf16_autocast": self.bf16,
                                                   "rows": self.rows})
        if plot and self.rows:
            plot_metrics(self.rows, self.run_dir / "loss.png")


def train_loop(model: nn.Module, step_fn: StepFn, dataset: Dataset, cfg: LoopConfig, run_dir: Path, *,
               collate_fn: Callable | None = None, augment: Callable[[dict, torch.Generator], dict] | None = None,
               val_fn: Callable[[nn.Module], dict[str, float]] | None = None, val_every: int = 0,
               resume: bool = False, device: str = "cpu",
               progress: Callable[[int, int, dict[str, float]], None] | None = None,
               extra_state: dict | None = None) -> TrainResult:
    """Train ``model`` for ``cfg.steps`` steps of ``step_fn`` over ``dataset`` (see the module docstring).

    Args:
        model: the network (moved to ``device``).
        step_fn: ``(model, batch) -> (loss, metrics)``; the batch is on ``device`` (after ``augment``).
        dataset: map-style dataset of dict items.
        cfg: loop settings.
        run_dir: output folder.
        collate_fn: batch collation (default: torch's default_collate).
        augment: ``(batch, generator) -> batch`` on the device, seeded per step.
        val_fn: ``model -> metrics`` run (eval mode, no grad, rank 0) every ``val_every`` steps and at the end.
        resume: continue from ``run_dir/checkpoints/last.pt`` (a fresh start when there is none).
        device: torch device string.
        progress: ``(step, total, metrics)`` callback after each step.
        extra_state: identity saved with each checkpoint and compared on resume (class list, model config).

    Raises:
        TrainingError: non-finite input/loss/gradient (naming the sample and step) or a mismatching checkpoint.
        ConfigError: ``run_dir`` already holds checkpoints and ``resume`` is False, or the loop settings changed.
    """
    t0 = time.perf_counter()
    rank, world = dist_setup(device)
    if cfg.batch_size % world:
        raise ConfigError(f"batch_size {cfg.batch_size} must be a multiple of the {world} DDP ranks")
    dev = torch.device(rank_device(device, int(os.environ.get("LOCAL_RANK", rank))) if world > 1 else device)
    if world > 1 and dev.type == "cuda":
        torch.cuda.set_device(dev)  # bare "cuda" elsewhere (val, pose eval) then means this rank's GPU
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed % 2**32)
    model.to(dev)
    run = _Run(model, cfg, run_dir, extra_state, rank)
    last = run.ckpt_dir / LAST
    if last.is_file() and not resume:
        raise ConfigError(f"{run_dir} already holds a training run; pass --resume to continue it or use a new --out")
    if resume and last.is_file():
        run.restore(last, dev)
    if world > 1:
        model = nn.parallel.DistributedDataParallel(model, device_ids=[dev.index] if dev.type == "cuda" else None)
        run.model = model
    if run.step >= cfg.steps:
        log.info("%s: already trained %d/%d steps", run_dir, run.step, cfg.steps)
        return TrainResult(Path(run_dir), run.step, math.nan, time.perf_counter() - t0, False)
    sampler = StepBatchSampler(len(dataset), cfg.steps, cfg.batch_size, cfg.seed, run.step, rank, world)
    loader = DataLoader(dataset, batch_sampler=sampler,
                        collate_fn=collate_fn or default_collate, num_workers=cfg.num_workers,
                        # its own generator: drawing the worker base seed must not advance the global RNG
                        generator=torch.Generator().manual_seed(cfg.seed + run.step))
    loss_v, interrupted = math.nan, False
    run.bf16 = cfg.amp and bf16_native(dev)
    if cfg.amp:
        log.info("bf16 autocast %s on %s", "on" if run.bf16 else "off (no native bf16: fp32)", dev)
    model.train()
    with stop_on_signals() as flag:
        try:
            for batch in loader:
                loss_v, metrics = _one_step(run, step_fn, batch, dev, augment, world)
                _after_step(run, loss_v, metrics, val_fn, val_every)
                if progress is not None:
                    progress(run.step, cfg.steps, {"loss": loss_v, **metrics})
                if flag["stop"] if world == 1 else any_rank(flag["stop"], dev):  # all ranks stop at one step
                    interrupted = True
                    break
        except KeyboardInterrupt:
            interrupted = True
    if interrupted:
        log.warning("interrupted at step %d: checkpoint written, continue with --resume", run.step)
    run.save(numbered=False)
    run.write_metrics(plot=True)
    if world > 1:  # no rank returns (and may resume) before rank 0 has written the last checkpoint
        dist.barrier()
    return TrainResult(Path(run_dir), run.step, loss_v, time.perf_counter() - t0, interrupted)


def _one_step(run: _Run, step_fn: StepFn, batch: dict, dev: torch.device,
              augment: Callable | None, world: int) -> tuple[float, dict[str, float]]:
    cfg = run.cfg
    check_finite_batch(batch, run.step)
    batch = to_device(batch, dev)
    if augment is not None:
        g = torch.Generator(device=dev).manual_seed(augment_seed(cfg.seed, run.step, run.rank))
        batch = augment(batch, g)
    with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=run.bf16):
        loss, metrics = step_fn(run.model, batch)
    if not bool(torch.isfinite(loss.detach()).all()):
        raise TrainingError(f"non-finite loss ({float(loss.detach())}) on sample {sample_names(batch)} at step "
                            f"{run.step}; check those samples and lower the learning rate; no checkpoint was written")
    run.opt.zero_grad(set_to_none=True)
    loss.float().backward()
    params = [p for p in run.model.parameters() if p.grad is not None]
    norm = torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip if cfg.grad_clip > 0 else float("inf"))
    if not bool(torch.isfinite(norm)):
        raise TrainingError(f"non-finite gradient on sample {sample_names(batch)} at step {run.step}; "
                            "lower the learning rate or enable grad_clip; no checkpoint was written")
    run.opt.step()
    run.sched.step()
    run.step += 1
    loss_v = float(loss.detach())
    if world > 1:
        t = torch.tensor([loss_v], device=dev)
        dist.all_reduce(t)
        loss_v = float(t) / world
    return loss_v, {k: float(v) for k, v in metrics.items()}


def _after_step(run: _Run, loss_v: float, metrics: dict[str, float], val_fn: Callable | None,
                val_every: int) -> None:
    cfg = run.cfg
    run.window.append(loss_v)
    do_val = val_fn is not None and run.rank == 0 and (
        (val_every > 0 and run.step % val_every == 0) or run.step == cfg.steps)
    if run.step % cfg.log_every == 0 or do_val or run.step == cfg.steps:
        row = {"step": run.step, "loss": loss_v, "loss_avg": float(np.mean(run.window)), **metrics,
               "lr": run.opt.param_groups[0]["lr"], "seconds": run.seconds(), "cpu_seconds": run.cpu_seconds()}
        if do_val:
            inner = unwrap(run.model)
            inner.eval()
            with torch.no_grad():
                row.update({f"val_{k}": float(v) for k, v in val_fn(inner).items()})
            inner.train()
        run.rows.append(row)
        run.window = []
        run.write_metrics(plot=False)
    if run.step % cfg.checkpoint_every == 0 and run.step < cfg.steps:
        run.save(numbered=True)

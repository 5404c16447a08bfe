"""Run a trainer as 2 gloo DDP ranks on CPU (torch.multiprocessing spawn) or as one process, and read its loss
curve. Each rank logs the checkpoint files it saves to ``ckpt_log/rank<r>.txt`` so tests can check that only
rank 0 writes them."""

from __future__ import annotations

import os
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cadalign.io import read_json  # noqa: F401  (re-exported for the tests)

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _logged_saves(log: Path) -> Callable[..., Any]:
    """``save_checkpoint`` that also appends the file name it writes to ``log``."""
    from cadalign.train import loop

    real = loop.save_checkpoint

    def save(path: Path, state: dict) -> Path:
        log.parent.mkdir(parents=True, exist_ok=True)
        with open(log, "a") as fh:
            fh.write(Path(path).name + "\n")
        return real(path, state)

    return save


def _worker(rank: int, world: int, port: int, target: Callable[..., Any], kwargs: dict, log_dir: str) -> None:
    import torch
    import torch.distributed as dist

    from cadalign.train import loop

    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1",
                      MASTER_PORT=str(port), OMP_NUM_THREADS="1")
    torch.set_num_threads(1)
    loop.save_checkpoint = _logged_saves(Path(log_dir) / f"rank{rank}.txt")  # this process only
    try:
        target(**kwargs)
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


def run_ddp(target: Callable[..., Any], kwargs: dict, log_dir: Path, world: int = 2, timeout_s: float = 120) -> None:
    """``target(**kwargs)`` in ``world`` spawned processes forming a gloo process group (as torchrun would).
    A rank that raises fails the call with its traceback; ranks still running after ``timeout_s`` (a
    collective that never pairs up) are terminated and the call fails."""
    import time

    import torch.multiprocessing as mp

    ctx = mp.spawn(_worker, args=(world, free_port(), target, kwargs, str(log_dir)), nprocs=world, join=False)
    deadline = time.monotonic() + timeout_s
    while not ctx.join(timeout=1.0):
        if time.monotonic() > deadline:
            for p in ctx.processes:
                p.terminate()
            raise TimeoutError(f"DDP ranks still running after {timeout_s} s (a hang between ranks?)")


def losses(run_dir: Path, key: str = "loss") -> list[float]:
    return [r[key] for r in read_json(run_dir / "metrics.json")["rows"]]


def saved(log_dir: Path, rank: int) -> list[str]:
    p = log_dir / f"rank{rank}.txt"
    return p.read_text().split() if p.is_file() else []


# Trainer entry points (module level: spawned processes import them by name).

def seg(cfg: Any, ds: Path, out: Path, resume: bool = False) -> None:
    from cadalign.train.seg import train_seg

    train_seg(cfg, ds, out, val_split=None, resume=resume)


def depth(cfg: Any, ds: Path, out: Path, resume: bool = False) -> None:
    from cadalign.train.depth import train_depth

    train_depth(cfg, ds, out, resume=resume)


def pose(cfg: Any, ds: Path, out: Path, resume: bool = False) -> None:
    from cadalign.train.pose import run

    run(cfg, ds, out, resume=resume)


def interrupted_then_resumed(trainer: str, cfg: Any, ds: Path, out: Path, stop_at: int) -> None:
    """Rank 0 alone gets SIGTERM after step ``stop_at`` (as a scheduler's signal reaching the ranks at
    different times): every rank must stop at that step; then all resume to ``cfg.loop.steps``."""
    import signal

    from cadalign.train.depth import train_depth
    from cadalign.train.seg import train_seg

    fn = {"seg": lambda **kw: train_seg(cfg, ds, out, val_split=None, **kw),
          "depth": lambda **kw: train_depth(cfg, ds, out, **kw)}[trainer]

    def progress(step: int, total: int, metrics: dict) -> None:
        if step == stop_at and int(os.environ["RANK"]) == 0:
            os.kill(os.getpid(), signal.SIGTERM)

    first = fn(progress=progress)
    assert first.interrupted and first.steps_done == stop_at, (os.environ["RANK"], first)
    second = fn(resume=True)
    assert not second.interrupted and second.steps_done == cfg.loop.steps, second


def toy_then(rest: Callable[..., Any], toy_out: Path, **kwargs: Any) -> None:
    """The exact toy check (:func:`toy`) into ``toy_out``, then ``rest(**kwargs)`` in the same process group."""
    toy(toy_out)
    rest(**kwargs)


class _Lin:
    """10 samples of y = 3 (x0 + x1) (a map-style dataset)."""

    def __len__(self) -> int:
        return 10

    def __getitem__(self, i: int) -> dict:
        import torch

        x = torch.tensor([float(i), 1.0 - i / 10])
        return {"x": x, "y": x.sum(0, keepdim=True) * 3, "im_id": i}


def _lin_step(model: Any, batch: dict) -> tuple[Any, dict[str, float]]:
    return ((model(batch["x"]) - batch["y"]) ** 2).mean(), {}


def toy(out: Path) -> None:
    """A linear model (no batch statistics, a per-sample mean loss): DDP must equal one process exactly."""
    import torch

    from cadalign.train.loop import LoopConfig, train_loop

    torch.manual_seed(0)
    cfg = LoopConfig(steps=6, batch_size=4, lr=1e-2, checkpoint_every=3, log_every=1, seed=2)
    train_loop(torch.nn.Linear(2, 1), _lin_step, _Lin(), cfg, out)


def trainers(cfgs: dict, ds: Path, root: Path) -> None:
    """Each trainer of ``cfgs`` (seg/depth/pose -> config) into ``root/<name>_ddp``, one after the other."""
    for name, cfg in cfgs.items():
        globals()[name](cfg, ds, root / f"{name}_ddp")

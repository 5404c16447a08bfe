"""Where training runs: the device of a DDP rank, process-group setup, the main rank, native bf16, and
moving batches to the device (used by :mod:`cadalign.train.loop`)."""

from __future__ import annotations

import os
from typing import Any

import torch
import torch.distributed as dist


def is_main_rank() -> bool:
    """True outside DDP and on rank 0: the process that writes run files."""

    return not (dist.is_available() and dist.is_initialized()) or dist.get_rank() == 0


def to_device(x: Any, device: torch.device) -> Any:
    """``x`` with every tensor in it (nested in dicts and lists) moved to ``device``."""
    if isinstance(x, torch.Tensor):
        return x.to(device, non_blocking=True)
    if isinstance(x, dict):
        return {k: to_device(v, device) for k, v in x.items()}
    if isinstance(x, list):
        return [to_device(v, device) for v in x]
    return x


def rank_device(device: str, local_rank: int) -> str:
    """The device of a DDP rank: a bare ``cuda`` becomes ``cuda:<LOCAL_RANK>`` (one GPU per rank on a node);
    an explicit index or another device type is kept."""
    return f"cuda:{local_rank}" if device == "cuda" else device


def dist_setup(device: str) -> tuple[int, int]:
    """(rank, world size): under ``torchrun`` (``RANK`` set, ``WORLD_SIZE`` > 1) the process group is joined (NCCL
    on CUDA, gloo on CPU); else (0, 1)."""
    if "RANK" not in os.environ or int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return 0, 1

    if not dist.is_initialized():
        dist.init_process_group("nccl" if device.startswith("cuda") else "gloo")
    return dist.get_rank(), dist.get_world_size()


def bf16_native(dev: torch.device) -> bool:
    """Whether ``dev`` computes bf16 natively: a CUDA GPU with bf16, a CPU with AVX512-BF16 or AMX tiles (there
    bf16 autocast cut a ResUNet step's CPU time by ~40 %; without them bf16 is emulated and slower)."""
    if dev.type == "cuda":
        return bool(torch.cuda.is_bf16_supported())
    if dev.type == "cpu":
        return any(bool(getattr(torch.cpu, f, lambda: False)()) for f in ("_is_avx512_bf16_supported",
                                                                          "_is_amx_tile_supported"))
    return False


def any_rank(flag: bool, dev: torch.device) -> bool:
    """Whether ``flag`` is set on any DDP rank (a signal may reach the ranks between different steps)."""

    t = torch.tensor([1.0 if flag else 0.0], device=dev)
    dist.all_reduce(t)
    return bool(t.item() > 0)

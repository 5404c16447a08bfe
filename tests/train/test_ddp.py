"""The training loop under DDP (2 gloo ranks on CPU) matches a single-process run step for step."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest
import torch
from torch import nn
from torch.utils.data import Dataset

from cadalign.io import read_json
from cadalign.train.loop import LoopConfig, train_loop

CFG = LoopConfig(steps=6, batch_size=4, lr=1e-2, checkpoint_every=3, log_every=1, seed=2)


class _Lin(Dataset):
    def __len__(self) -> int:
        return 10

    def __getitem__(self, i: int) -> dict:
        x = torch.tensor([float(i), 1.0 - i / 10])
        return {"x": x, "y": x.sum(0, keepdim=True) * 3, "im_id": i}


def _model() -> nn.Module:
    torch.manual_seed(0)
    return nn.Linear(2, 1)


def _step(model: nn.Module, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
    return ((model(batch["x"]) - batch["y"]) ** 2).mean(), {}


def _worker(rank: int, world: int, port: int, run_dir: str) -> None:
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.set_num_threads(1)
    import torch.distributed as dist

    try:
        train_loop(_model(), _step, _Lin(), CFG, Path(run_dir))
    finally:
        if dist.is_initialized():
            dist.destroy_process_group()


@pytest.mark.slow
def test_ddp_two_ranks_match_single_process(tmp_path):
    import torch.multiprocessing as mp

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    mp.spawn(_worker, args=(2, port, str(tmp_path / "ddp")), nprocs=2, join=True)
    train_loop(_model(), _step, _Lin(), CFG, tmp_path / "single")
    ddp = [r["loss"] for r in read_json(tmp_path / "ddp" / "metrics.json")["rows"]]
    single = [r["loss"] for r in read_json(tmp_path / "single" / "metrics.json")["rows"]]
    assert ddp == pytest.approx(single, rel=1e-5)
    assert (tmp_path / "ddp" / "checkpoints" / "step_000003.pt").is_file()

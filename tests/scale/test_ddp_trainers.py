"""2-rank CPU DDP (gloo, torch.multiprocessing spawn, as torchrun sets it up) of the trainers against one process
with the same global batch.

Exact equality holds for a model without batch statistics (the toy linear model). The seg and depth networks
use BatchNorm, which under DDP normalises each rank's half batch (SyncBatchNorm is CUDA-only in torch), and the
Mask R-CNN samples anchors and RoIs per process, so their curves agree within a tolerance. Measured at lr 1e-3
on the reference build of conftest (12 frames, 320x240): step 1 within 0.02 % (seg) / 0.3 % (depth) /
0.5 % (pose), 6 steps within 3 %; on a 6-frame 160x120 simulator scene: step 1 within 0.6 % / 0.06 % / 0.7 %,
6 steps within 3.5 %.
"""

from __future__ import annotations

from pathlib import Path

import ddp_testutils as U
import pytest

from cadalign.config import resolve
from cadalign.train.loop import augment_seed, rank_device

LOOP = {"steps": 6, "batch_size": 2, "lr": 1e-3, "log_every": 1, "checkpoint_every": 2, "seed": 3}
FIRST_TOL = {"seg": 0.02, "depth": 0.01, "pose": 0.02}
CURVE_TOL = 0.06


def tiny_configs() -> dict:
    from cadalign.train.depth import PRESETS as DEPTH
    from cadalign.train.depth import DepthTrainConfig
    from cadalign.train.pose import PRESETS as POSE
    from cadalign.train.pose import PoseTrainConfig
    from cadalign.train.seg import PRESETS as SEG
    from cadalign.train.seg import SegTrainConfig

    over = {"loop": LOOP, "augment": {"enabled": False}}  # augmentation draws per rank, not per sample
    t = U.REPO / "training"
    return {"seg": resolve(SegTrainConfig, SEG, "fast", t / "seg_tiny.toml", {**over, "patch": None}),
            "depth": resolve(DepthTrainConfig, DEPTH, "fast", t / "depth_tiny.toml", over),
            "pose": resolve(PoseTrainConfig, POSE, "fast", t / "pose_tiny.toml", over)}


def assert_same_curve(name: str, ddp: list[float], single: list[float]) -> None:
    assert len(ddp) == len(single) == LOOP["steps"], (ddp, single)
    assert ddp[0] == pytest.approx(single[0], rel=FIRST_TOL[name]), (name, ddp, single)
    assert ddp == pytest.approx(single, rel=CURVE_TOL), (name, ddp, single)


def assert_rank0_checkpoints(log_dir: Path, run: Path) -> None:
    assert U.saved(log_dir, 1) == []
    names = set(U.saved(log_dir, 0))
    assert {"step_000002.pt", "step_000004.pt", "last.pt"} <= names
    assert {p.name for p in (run / "checkpoints").iterdir()} == names


def test_augment_seed_differs_per_rank_and_keeps_rank0() -> None:
    assert augment_seed(3, 5, 0) == 3 * 7_919 + 5 * 104_729 + 1  # the single-process seed, unchanged
    seeds = {augment_seed(3, s, r) for s in range(50) for r in range(4)}
    assert len(seeds) == 200


def test_each_rank_gets_its_own_gpu_and_cpu_stays_cpu() -> None:
    assert [rank_device("cuda", r) for r in range(3)] == ["cuda:0", "cuda:1", "cuda:2"]
    assert rank_device("cuda:3", 1) == "cuda:3" and rank_device("cpu", 1) == "cpu"


def test_ddp_depth_interrupted_on_one_rank_resumes_to_the_single_process_curve(ddp_scene: Path,
                                                                              tmp_path: Path) -> None:
    """One spawn (~20 s here, mostly process start): the toy model must match one process exactly; then the
    depth trainer, with SIGTERM reaching rank 0 alone after step 3: both ranks stop there, rank 0 alone writes
    checkpoints, and the resumed run's curve matches one uninterrupted process."""
    from cadalign.train.depth import train_depth

    cfg = tiny_configs()["depth"]
    U.run_ddp(U.toy_then, {"toy_out": tmp_path / "toy_ddp", "rest": U.interrupted_then_resumed, "trainer": "depth",
                           "cfg": cfg, "ds": ddp_scene, "out": tmp_path / "ddp", "stop_at": 3}, tmp_path / "log")
    U.toy(tmp_path / "toy_single")
    assert U.losses(tmp_path / "toy_ddp") == pytest.approx(U.losses(tmp_path / "toy_single"), rel=1e-5)
    train_depth(cfg, ddp_scene, tmp_path / "single")
    assert_same_curve("depth", U.losses(tmp_path / "ddp"), U.losses(tmp_path / "single"))
    assert [r["step"] for r in U.read_json(tmp_path / "ddp" / "metrics.json")["rows"]] == [1, 2, 3, 4, 5, 6]
    assert U.saved(tmp_path / "log", 1) == []
    assert "step_000002.pt" in U.saved(tmp_path / "log", 0) and "last.pt" in U.saved(tmp_path / "log", 0)


@pytest.mark.slow
def test_ddp_each_trainer_matches_single_process(ddp_scene: Path, tmp_path: Path) -> None:
    """seg, depth and pose, 6 steps each, in one 2-rank spawn (~30 s here) and in this process."""
    cfgs = tiny_configs()
    for name in cfgs:
        getattr(U, name)(cfgs[name], ddp_scene, tmp_path / f"{name}_single")
    U.run_ddp(U.trainers, {"cfgs": cfgs, "ds": ddp_scene, "root": tmp_path}, tmp_path / "log")
    for name in cfgs:
        assert_same_curve(name, U.losses(tmp_path / f"{name}_ddp"), U.losses(tmp_path / f"{name}_single"))
    saves = U.saved(tmp_path / "log", 0)
    assert U.saved(tmp_path / "log", 1) == [] and saves.count("step_000004.pt") == 3
    assert (tmp_path / "pose_ddp" / "eval_heldout.json").is_file()

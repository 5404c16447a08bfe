"""Resuming a training run made before a config field existed: accepted at the field's default only."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import pytest
import torch

from cadalign.errors import ConfigError, TrainingError
from cadalign.io import read_json, write_json
from cadalign.models.resunet import ResUNetConfig
from cadalign.train.checkpoint import check_extra_state, load_checkpoint, save_checkpoint
from cadalign.train.common import RUN_CONFIG, write_run_record
from cadalign.train.loop import LoopConfig, train_loop


class _Line(torch.utils.data.Dataset):
    def __len__(self) -> int:
        return 6

    def __getitem__(self, i: int) -> dict:
        x = torch.full((2,), float(i))
        return {"x": x, "y": x.sum(0, keepdim=True)}


def _step(model: torch.nn.Module, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
    return ((model(batch["x"]) - batch["y"]) ** 2).mean(), {}


def _model() -> torch.nn.Module:
    torch.manual_seed(0)
    return torch.nn.Linear(2, 1)


CFG = LoopConfig(steps=2, batch_size=2, lr=1e-2, checkpoint_every=1, log_every=1, seed=1)


def _forget_in_checkpoint(run, key: str) -> None:
    """Make ``run``'s last checkpoint look written before the LoopConfig field ``key`` existed."""
    path = run / "checkpoints" / "last.pt"
    ck = load_checkpoint(path)
    del ck["loop_config"][key]
    save_checkpoint(path, ck)


def test_loop_resumes_a_checkpoint_lacking_a_defaulted_field(tmp_path):
    extra = {"classes": ["bg", "valve"], "model": ResUNetConfig()}
    train_loop(_model(), _step, _Line(), CFG, tmp_path, extra_state=extra)
    _forget_in_checkpoint(tmp_path, "warmup")
    assert load_checkpoint(tmp_path / "checkpoints" / "last.pt")["extra_state"]["model"] == ResUNetConfig().__dict__
    res = train_loop(_model(), _step, _Line(), replace(CFG, steps=4), tmp_path, resume=True, extra_state=extra)
    assert res.steps_done == 4
    assert load_checkpoint(tmp_path / "checkpoints" / "last.pt")["step"] == 4


def test_loop_refuses_the_missing_field_at_a_non_default_value(tmp_path):
    train_loop(_model(), _step, _Line(), CFG, tmp_path)
    _forget_in_checkpoint(tmp_path, "warmup")
    with pytest.raises(ConfigError, match=r"other loop settings \(warmup: '<missing>' -> 0\.3\)"):
        train_loop(_model(), _step, _Line(), replace(CFG, steps=4, warmup=0.3), tmp_path, resume=True)
    with pytest.raises(ConfigError, match=r"lr: 0\.01 -> 0\.5"):  # a changed value, as before
        train_loop(_model(), _step, _Line(), replace(CFG, steps=4, lr=0.5), tmp_path, resume=True)


def test_extra_state_model_config_lacking_a_field():
    saved = {"classes": ["bg"], "model": ResUNetConfig().__dict__}
    del saved["model"]["base_channels"]  # a checkpoint older than that field
    check_extra_state(saved, {"classes": ["bg"], "model": ResUNetConfig()}, "ck.pt")
    wider = replace(ResUNetConfig(), base_channels=ResUNetConfig().base_channels * 2)
    with pytest.raises(TrainingError, match=r"different model \(differs in: base_channels\)"):
        check_extra_state(saved, {"classes": ["bg"], "model": wider}, "ck.pt")
    with pytest.raises(TrainingError, match="different classes"):
        check_extra_state(saved, {"classes": ["bg", "pipe"], "model": ResUNetConfig()}, "ck.pt")
    with pytest.raises(TrainingError, match="checkpoint has '<missing>'"):
        check_extra_state({}, {"classes": ["bg"]}, "ck.pt")


@dataclass(frozen=True)
class _TaskConfig:
    loop: LoopConfig = field(default_factory=LoopConfig)
    """The loop."""
    scale: float = 0.5
    """Image scale."""
    dice_weight: float = 1.0
    """A field added after the run was made."""


def _old_record(out, cfg: _TaskConfig) -> None:
    write_run_record(out, "seg", cfg, {"classes": ["bg"], "model": ResUNetConfig()}, {}, resume=False)
    record = read_json(out / RUN_CONFIG)
    del record["config"]["dice_weight"]
    del record["model"]["base_channels"]
    write_json(out / RUN_CONFIG, record)


def test_run_record_resumes_a_record_lacking_defaulted_fields(tmp_path):
    _old_record(tmp_path, _TaskConfig())
    longer = _TaskConfig(loop=LoopConfig(steps=900))  # more steps are allowed on resume
    write_run_record(tmp_path, "seg", longer, {"classes": ["bg"], "model": ResUNetConfig()}, {}, resume=True)
    rec = read_json(tmp_path / RUN_CONFIG)
    assert rec["config"]["dice_weight"] == 1.0 and rec["config"]["loop"]["steps"] == 900
    assert rec["model"] == ResUNetConfig().__dict__


def test_run_record_refuses_the_missing_field_at_a_non_default_value(tmp_path):
    _old_record(tmp_path, _TaskConfig())
    with pytest.raises(ConfigError, match=r"another config \(differs in: config\.dice_weight\)"):
        write_run_record(tmp_path, "seg", _TaskConfig(dice_weight=2.0), {"classes": ["bg"], "model": ResUNetConfig()},
                         {}, resume=True)
    with pytest.raises(ConfigError, match=r"differs in: config\.scale\)"):
        write_run_record(tmp_path, "seg", _TaskConfig(scale=1.0), {"classes": ["bg"], "model": ResUNetConfig()}, {},
                         resume=True)

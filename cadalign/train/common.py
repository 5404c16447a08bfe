"""Pieces shared by the segmentation and depth trainers: the run record and the device/threads setup."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cadalign._version import __version__
from cadalign.config import config_differences, to_dict
from cadalign.errors import ConfigError
from cadalign.io import read_json, write_json
from cadalign.train.checkpoint import LAST, check_extra_state
from cadalign.train.loop import RESUMABLE_CHANGES

RUN_CONFIG = "train_config.json"


def write_run_record(out: Path, task: str, cfg: Any, identity: dict[str, Any], extra: dict[str, Any], *,
                     resume: bool) -> Path:
    """Write ``out/train_config.json`` (task, resolved config, identity, extras, version).

    A folder holding a checkpoint is refused unless ``resume`` (nothing is overwritten). On resume the folder's
    record must have the same ``identity`` (class list, model config: else
    :class:`TrainingError`) and the same config up to the loop's ``steps``/logging (else :class:`ConfigError`).
    """
    out = Path(out)
    record = to_dict({"task": task, "config": cfg, **identity, **extra, "version": __version__})
    path = out / RUN_CONFIG
    if not resume and (out / "checkpoints" / LAST).is_file():
        raise ConfigError(f"{out} already holds a training run; pass --resume to continue it or use a new --out")
    if resume and path.is_file():
        old = read_json(path)
        check_extra_state(old, identity, path)
        keys = [f"config.{k}" for k in config_differences(old.get("config"), cfg) if k not in _RESUMABLE]
        if keys:
            raise ConfigError(f"{out} was trained with another config (differs in: {', '.join(keys)}); "
                              "resume with the same preset/--config or use a new --out")
    write_json(path, record)
    return path


_RESUMABLE = {f"loop.{k}" for k in RESUMABLE_CHANGES} | {"val_every"}
"""Config keys a resumed run may change (how long and how often it logs, not what it learns)."""

"""The run record shared by the segmentation, depth and pose trainers (``RUN/train_config.json``)."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from cadalign._version import __version__
from cadalign.config import config_differences, to_dict
from cadalign.errors import ConfigError
from cadalign.io import read_json, write_json
from cadalign.train.checkpoint import LAST, check_extra_state
from cadalign.train.loop import RESUMABLE_CHANGES

RUN_CONFIG = "train_config.json"


RUN_FILES = (RUN_CONFIG, "metrics.json", "loss.png", "eval_heldout.json")
"""What a training run writes beside ``checkpoints/`` (``--overwrite`` removes them with it)."""


def write_run_record(out: Path, task: str, cfg: Any, identity: dict[str, Any], extra: dict[str, Any], *,
                     resume: bool, overwrite: bool = False) -> Path:
    """Write ``out/train_config.json`` (task, resolved config, identity, extras, version).

    A folder holding a checkpoint is refused unless ``resume`` (continue it) or ``overwrite`` (the old run's
    checkpoints and records are deleted first; with ``resume`` too, ``resume`` wins). On resume the folder's
    record must have the same ``identity`` (class list, model config: else :class:`TrainingError`) and the same
    config up to the loop's ``steps``/logging (else :class:`ConfigError`).
    """
    out = Path(out)
    record = to_dict({"task": task, "config": cfg, **identity, **extra, "version": __version__})
    path = out / RUN_CONFIG
    if overwrite and not resume:
        shutil.rmtree(out / "checkpoints", ignore_errors=True)
        for name in RUN_FILES:
            (out / name).unlink(missing_ok=True)
    if not resume and (out / "checkpoints" / LAST).is_file():
        raise ConfigError(f"{out} already holds a training run; pass --resume to continue it, --overwrite to "
                          "replace it, or use a new --out")
    if resume and path.is_file():
        old = read_json(path)
        # a record written before a key joined the identity is not refused for it (the checkpoint is checked too)
        check_extra_state(old, {k: v for k, v in identity.items() if k in old}, path)
        keys = [f"config.{k}" for k in config_differences(old.get("config"), cfg) if k not in _RESUMABLE]
        if keys:
            raise ConfigError(f"{out} was trained with another config (differs in: {', '.join(keys)}); "
                              "resume with the same preset/--config, pass --overwrite without --resume to "
                              "replace the run, or use a new --out")
    write_json(path, record)
    return path


_RESUMABLE = {f"loop.{k}" for k in RESUMABLE_CHANGES} | {"val_every"}
"""Config keys a resumed run may change (how long and how often it logs, not what it learns)."""

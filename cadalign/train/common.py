"""Pieces shared by the segmentation and depth trainers: the run record and the device/threads setup."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cadalign._version import __version__
from cadalign.config import to_dict
from cadalign.errors import ConfigError
from cadalign.io import read_json, write_json
from cadalign.train.checkpoint import LAST, check_extra_state

RUN_CONFIG = "train_config.json"


def write_run_record(out: Path, task: str, cfg: Any, identity: dict[str, Any], extra: dict[str, Any], *,
                     resume: bool) -> Path:
    """Write ``out/train_config.json`` (task, resolved config, identity, extras, version).

    A folder holding a checkpoint is refused unless ``resume`` (nothing is overwritten). On resume the folder's
    record must have the same ``identity`` (class list, model config: else
    :class:`TrainingError`) and the same config up to the loop's ``steps``/logging (else :class:`ConfigError`).
    """
    out = Path(out)
    record = {"task": task, "config": to_dict(cfg), **identity, **extra, "version": __version__}
    path = out / RUN_CONFIG
    if not resume and (out / "checkpoints" / LAST).is_file():
        raise ConfigError(f"{out} already holds a training run; pass --resume to continue it or use a new --out")
    if resume and path.is_file():
        old = read_json(path)
        check_extra_state(old, identity, path)
        a, b = _comparable(old, identity), _comparable(record, identity)
        if a != b:
            keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            raise ConfigError(f"{out} was trained with another config (differs in: {', '.join(keys)}); "
                              "resume with the same preset/--config or use a new --out")
    write_json(path, record)
    return path


def _comparable(rec: dict[str, Any], identity: dict[str, Any]) -> dict[str, Any]:
    flat: dict[str, Any] = {}

    def walk(prefix: str, v: Any) -> None:
        if isinstance(v, dict):
            for k, x in v.items():
                walk(f"{prefix}.{k}" if prefix else str(k), x)
        else:
            flat[prefix] = v

    walk("", {k: v for k, v in rec.items() if k == "config"})
    for k in ("config.loop.steps", "config.loop.checkpoint_every", "config.loop.log_every", "config.loop.num_workers",
              "config.val_every"):
        flat.pop(k, None)
    return flat

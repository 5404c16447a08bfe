"""Pieces shared by the segmentation and depth trainers: the run record and the device/threads setup."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cadalign._version import __version__
from cadalign.config import to_dict
from cadalign.errors import ConfigError
from cadalign.io import read_json, write_json

RUN_CONFIG = "train_config.json"


def write_run_record(out: Path, task: str, cfg: Any, extra: dict[str, Any], *, resume: bool) -> Path:
    """Write ``out/train_config.json`` (task, resolved config, identity, version); refuse another config on resume.

    The loop's ``steps`` may change on resume (to train longer); anything else must match.

    Raises:
        ConfigError: ``resume`` and the folder was trained with another task or config.
    """
    out = Path(out)
    record = {"task": task, "config": to_dict(cfg), **extra, "version": __version__}
    path = out / RUN_CONFIG
    if resume and path.is_file():
        old = read_json(path)
        a, b = _comparable(old), _comparable(record)
        if a != b:
            keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            raise ConfigError(f"{out} was trained with another config (differs in: {', '.join(keys)}); "
                              "resume with the same preset/--config or use a new --out")
    write_json(path, record)
    return path


def _comparable(rec: dict[str, Any]) -> dict[str, Any]:
    flat: dict[str, Any] = {}

    def walk(prefix: str, v: Any) -> None:
        if isinstance(v, dict):
            for k, x in v.items():
                walk(f"{prefix}.{k}" if prefix else str(k), x)
        else:
            flat[prefix] = v

    walk("", {k: v for k, v in rec.items() if k != "version"})
    for k in ("config.loop.steps", "config.loop.checkpoint_every", "config.loop.log_every", "config.loop.num_workers",
              "config.val_every", "dataset"):
        flat.pop(k, None)
    return {k: v for k, v in flat.items() if not k.startswith("dataset.")}

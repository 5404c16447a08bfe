"""Training checkpoints: atomic save/load with RNG states and an ``extra_state`` identity check.

A checkpoint is one ``torch.save`` dict written to a temporary file and moved into place, so an
interrupted write never leaves a half-written ``last.pt``. ``extra_state`` (class list, model config, …)
is compared key by key on resume and on evaluation so a checkpoint of another model or class list is
refused with a message naming the differing key.
"""

from __future__ import annotations

import logging
import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from cadalign.config import config_differences, to_dict
from cadalign.errors import TrainingError
from cadalign.io import atomic_path

log = logging.getLogger(__name__)

LAST = "last.pt"


def unwrap(model: nn.Module) -> nn.Module:
    """The plain module inside a DistributedDataParallel (or the model itself)."""
    return model.module if hasattr(model, "module") and isinstance(model.module, nn.Module) else model


def rng_state() -> dict[str, Any]:
    """The python, numpy and torch (CPU and CUDA) RNG states."""
    state: dict[str, Any] = {"python": random.getstate(), "numpy": np.random.get_state(),
                             "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: Path, state: dict[str, Any]) -> Path:
    """Write ``state`` with ``torch.save`` atomically (temp file + rename).

    Raises:
        TrainingError: the write failed (a full disk shows up as torch's bare "iostream error"); the message
            names the file and the free space, and the checkpoint already there is left as it was.
    """
    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            torch.save(state, tmp)
    except (OSError, RuntimeError) as exc:
        try:
            free = f"{shutil.disk_usage(path.parent).free / 2**20:.0f} MiB free there"
        except OSError:
            free = "free space unknown"
        raise TrainingError(f"could not write the checkpoint {path} ({exc}; {free}). The previous checkpoint is "
                            "intact: free disk space, then continue with --resume") from exc
    return path


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Raises:
        TrainingError: the file is missing or unreadable.
    """
    path = Path(path)
    if not path.is_file():
        raise TrainingError(f"checkpoint not found: {path} (train first, or point --model at a run folder)")
    try:
        # weights_only=False: the checkpoint holds RNG states (numpy tuples) written by this package.
        return torch.load(path, map_location=map_location, weights_only=False)
    except Exception as exc:  # torch raises many types for corrupt files
        raise TrainingError(f"{path} is not a readable checkpoint ({exc}); delete it or retrain") from exc


def check_extra_state(saved: dict[str, Any] | None, expected: dict[str, Any] | None, source: Path) -> None:
    """Refuse a checkpoint whose ``extra_state`` differs from ``expected`` in any key ``expected`` has.

    Values of ``expected`` may be config dataclasses (the model config); they are compared with the saved
    ``to_dict`` form through :func:`cadalign.config.config_differences`, so a model-config field added later
    with a default does not refuse checkpoints saved before it existed.

    Raises:
        TrainingError: naming the first differing key and both values.
    """
    saved = saved or {}
    for key, want in (expected or {}).items():
        if key not in saved:
            raise TrainingError(
                f"{source} was trained with a different {key}: checkpoint has '<missing>', this run has "
                f"{to_dict(want)!r}; use a new --out folder (or the matching dataset/model settings)"
            )
        have = saved[key]
        differs = config_differences(have, want)
        if differs:
            fields = f" (differs in: {', '.join(differs)})" if differs != [""] else ""
            raise TrainingError(
                f"{source} was trained with a different {key}{fields}: checkpoint has {have!r}, this run has "
                f"{to_dict(want)!r}; use a new --out folder (or the matching dataset/model settings)"
            )

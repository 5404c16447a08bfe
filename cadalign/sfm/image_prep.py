"""How a dataset's images were prepared, so that a network trained on them is fed new frames prepared alike.

A built dataset's ``rgb/`` images are the SfM stage's frames, which SfM enhanced for murky water
(``frames.enhance``: CLAHE in every preset); a simulator's truth holds the raw rendered frames. A network trained
on enhanced images and run on raw video loses much of its accuracy (the default scene's detector: valve F1 0.902
on the dataset's images, 0.676 on the raw frames), so the preparation travels with the data:

- ``build-dataset`` writes ``images.json`` at the dataset root (:func:`write_record`);
- ``cadalign train`` copies it into the run's ``train_config.json`` (key ``images``);
- ``cadalign infer`` with ``enhance = "auto"`` reads it from the run and prepares each raw frame the same way.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.errors import InputError
from cadalign.io import read_json, write_json
from cadalign.sfm.config import FrameConfig
from cadalign.sfm.frames import enhance

log = logging.getLogger(__name__)

RECORD = "images.json"
ENHANCE = ("none", "clahe", "clahe_wb")
RAW: dict[str, Any] = {"enhance": "none"}


def prep_of_frame_config(frames: Any) -> dict[str, Any]:
    """The record of an SfM :class:`~cadalign.sfm.config.FrameConfig` (or its dict form)."""
    get = frames.get if isinstance(frames, dict) else lambda k: getattr(frames, k)
    how = get("enhance")
    return dict(RAW) if how == "none" else {"enhance": how, "clahe_clip": float(get("clahe_clip")),
                                            "clahe_tiles": int(get("clahe_tiles"))}


def prep_named(enhance: str) -> dict[str, Any]:
    """The record of one enhancement with SfM's default settings (``FrameConfig``'s CLAHE clip and tiles)."""

    return prep_of_frame_config(FrameConfig(enhance=enhance))


def write_record(dataset_root: Path, prep: dict[str, Any], source: str) -> Path:
    """``dataset_root/images.json``: the preparation of the dataset's images and where they came from."""
    return write_json(Path(dataset_root) / RECORD, {**_checked(prep, str(dataset_root)), "source": source})


def _checked(prep: Any, where: str) -> dict[str, Any]:
    if not isinstance(prep, dict) or prep.get("enhance") not in ENHANCE:
        raise InputError(f"{where}: the image preparation {prep!r} is not one of enhance = {', '.join(ENHANCE)}; "
                         f"rebuild the dataset or delete {RECORD}")
    return prep_of_frame_config({**prep_named(prep["enhance"]), **prep})


def read_prep(scene_or_root: Path) -> dict[str, Any] | None:
    """The preparation of the images of a dataset (its root or one of its BOP scene folders), or None if unknown.

    Looked up in order: ``images.json`` at or above the folder (two levels: ``root/all/000000``); a simulator's
    truth (``sim_report.json`` up to three levels above: raw frames); a dataset built before the record
    existed (the SfM stage's settings in ``../sfm/cadalign_stage.json`` beside the dataset root).
    """
    p = Path(scene_or_root).resolve()
    ups = [p, *list(p.parents)[:3]]
    for root in ups[:3]:
        if (root / RECORD).is_file():
            return _checked(read_json(root / RECORD), str(root / RECORD))
    for root in ups:
        if (root / "sim_report.json").is_file():
            return dict(RAW)
    for root in ups[:3]:
        stage = root.parent / "sfm" / "cadalign_stage.json"
        if (root / "cadalign_stage.json").is_file() and stage.is_file():
            frames = read_json(stage).get("config", {}).get("sfm", {}).get("frames")
            if isinstance(frames, dict) and "enhance" in frames:
                return prep_of_frame_config(frames)
    return None


def read_run_prep(run: Path) -> dict[str, Any] | None:
    """The preparation of a training run's images (``run``: its folder or one of its checkpoints,
    ``RUN/checkpoints/*.pt``): its ``train_config.json`` record (``images``), else that of the dataset the run
    names, when it still exists; None when neither says."""
    run = Path(run)
    path = (run if run.is_dir() else run.parent.parent) / "train_config.json"
    rec = read_json(path) if path.is_file() else {}
    if rec.get("images") is not None:
        return _checked(rec["images"], str(path))
    if rec.get("dataset") and Path(rec["dataset"]).exists():
        return read_prep(Path(rec["dataset"]))
    return None


def to_feed(source: dict[str, Any] | None, trained: dict[str, Any] | None, what: str) -> dict[str, Any]:
    """The preparation that makes images prepared as ``source`` look like a network's training images
    (``trained``): none when they agree or either is unknown, ``trained`` for raw images; an enhanced source that
    the network was not trained on cannot be undone, so it is fed as it is, with a warning naming ``what``. Raw
    frames for a network whose run does not say (``trained`` None) are fed raw with a warning too, as ``infer``
    warns (they may have needed the CLAHE of a built dataset)."""
    if trained is None and source is not None and source["enhance"] == "none":
        log.warning("%s does not record how its training images were prepared; raw frames are fed as they are. If "
                    "it was trained on a built dataset (CLAHE-enhanced by SfM), retrain it or use a run that says",
                    what)
    if source is None or trained is None or source == trained:
        return dict(RAW)
    if source["enhance"] == "none":
        return trained
    log.warning("%s: the images are prepared as %s but the network was trained on images prepared as %s; they are "
                "fed as they are (use the raw frames, e.g. the simulator's truth, to have them prepared alike)",
                what, source, trained)
    return dict(RAW)


def apply(rgb: np.ndarray, prep: dict[str, Any]) -> np.ndarray:
    """An (H, W, 3) uint8 RGB frame prepared as ``prep`` says (:func:`cadalign.sfm.frames.enhance`)."""
    if prep["enhance"] == "none":
        return rgb

    return enhance(rgb, FrameConfig(enhance=prep["enhance"], clahe_clip=prep["clahe_clip"],
                                    clahe_tiles=prep["clahe_tiles"]))

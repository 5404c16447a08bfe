"""Training the Mask R-CNN + pose network on a BOP dataset (``cadalign train pose``).

``run(cfg, dataset, out_dir)`` trains with the shared loop (:mod:`cadalign.train.loop`) and then scores
the held-out frames (val + test, never used in training; ``eval_heldout.json``, at the images' own resolution,
scored by :func:`cadalign.metrics.pose_eval.evaluate_scene` with the rules of ``cadalign eval pose``: detection
precision/recall/F1 at IoU 0.5, mask IoU, translation and rotation errors, BOP recalls, per class).
The dataset is a ``cadalign build-dataset`` folder
(``splits.json``, ``models/``) or one BOP scene folder (e.g. the simulator's ``gt/sim/000000``, models in
``../../models``), with the same frame selection as the dense trainers (:func:`cadalign.train.data.select`).

Images, masks, boxes and K are resized to the network input once per frame and cached in memory (a build
dataset is at most a few hundred frames). No flips: mirroring changes the handedness of the pose.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from torch import nn
from torch.utils.data import Dataset

from cadalign.cad.models_info import symmetry_from_entry
from cadalign.config import bounded
from cadalign.errors import InputError
from cadalign.formats.bop import mask_bbox
from cadalign.io import read_json, write_json
from cadalign.models.maskrcnn.detector import MODEL_KIND, MaskRCNNConfig, MaskRCNNPose
from cadalign.sfm.image_prep import read_prep
from cadalign.train.augment import AugmentConfig, colour_jitter
from cadalign.train.common import write_run_record
from cadalign.train.data import select
from cadalign.train.datasets import DetectionPoseDataset, detection_collate
from cadalign.train.loop import LoopConfig, TrainResult, is_main_rank, train_loop
from cadalign.train.pose_crop import crop_batch
from cadalign.train.pose_eval import evaluate
from cadalign.train.pose_losses import ObjectGeometry, PoseLoss, PoseLossConfig

log = logging.getLogger(__name__)

MM_TO_M = 1e-3


@dataclass(frozen=True)
class PoseTrainConfig:
    model: MaskRCNNConfig = field(default_factory=MaskRCNNConfig)
    """The network (backbone, heads, input size, pose parameterisation)."""
    loop: LoopConfig = field(default_factory=LoopConfig)
    """Optimiser steps, batch size, learning rate, checkpoints."""
    loss: PoseLossConfig = field(default_factory=PoseLossConfig)
    """Pose-loss weights and symmetry sampling."""
    augment: AugmentConfig = field(default_factory=lambda: AugmentConfig(hflip=0.0, turbidity=0.0, crop_prob=0.0))
    """Colour jitter only (flips and crops are not used for poses)."""
    model_points: int = bounded(500, ge=8)
    """CAD surface points per object for the point-matching loss."""
    eval_score_thresh: float = bounded(0.5, ge=0, le=1)
    """Score threshold of the held-out evaluation."""
    crop_hw: tuple[int, int] | None = None
    """(height, width) of random training crops of the ``model.input_hw`` image, or None for whole images. Crops
    keep small parts at the scale the network sees at inference (on the whole ``input_hw`` frame) at the cost
    per step of the crop size; poses are unchanged (K's principal point moves), see :mod:`cadalign.train.pose_crop`."""
    crop_object_prob: float = bounded(0.8, ge=0, le=1)
    """Probability that a crop is placed around a randomly chosen instance (else uniformly)."""
    crop_balance_classes: bool = False
    """Draw the instance a crop is placed around class-balanced (a class present in the frame uniformly, then one of its
    instances) instead of uniformly over instances. Off: hot stab F1 rose a little, fused rotations got worse
    (docs/tuning/train_config.md#posetrainconfigcrop_balance_classes)."""
    zoom_prob: float = bounded(0.0, ge=0, le=1)
    """Probability that a training crop is zoomed in: a window ``z`` times smaller than ``crop_hw`` (or ``input_hw``),
    ``z`` log-uniform in ``[1, zoom_max]``, upsampled to it, so parts look ``z`` times closer (K scales, the pose stays;
    :mod:`cadalign.train.pose_crop`)."""
    zoom_max: float = bounded(2.0, ge=1)
    """Largest zoom factor of ``zoom_prob``."""
    rotate_prob: float = bounded(0.0, ge=0, le=1)
    """Probability that a training frame is rolled about its optical axis by up to ``rotate_max_deg`` (an exact
    homography; ``R``, ``t`` turn with it; :mod:`cadalign.train.pose_crop`). Off: recall rose but F1 and fused rotations
    fell (docs/tuning/train_config.md#posetrainconfigrotate_prob)."""
    rotate_max_deg: float = bounded(30.0, ge=0, le=180)
    """Largest roll of ``rotate_prob`` (degrees, uniform in ``[-max, max]``)."""
    paste_prob: float = bounded(0.0, ge=0, le=1)
    """Probability that a training frame gets instances of the next frame of its batch pasted in where they are
    (:func:`cadalign.train.pose_crop.paste_instances`; needs ``loop.batch_size`` >= 2). Off: F1 fell and a step costs
    more (docs/tuning/train_config.md#posetrainconfigpaste_prob)."""
    paste_max: int = bounded(3, ge=1)
    """Instances pasted per pasted frame at most (class-balanced draws from the donor frame)."""

    def __post_init__(self) -> None:
        if self.crop_hw is not None and (self.crop_hw[0] > self.model.input_hw[0]
                                         or self.crop_hw[1] > self.model.input_hw[1]):
            raise ValueError(f"crop_hw {tuple(self.crop_hw)} must fit in model.input_hw {tuple(self.model.input_hw)}")
        if self.paste_prob > 0 and self.loop.batch_size < 2:
            raise ValueError(f"paste_prob {self.paste_prob} pastes from the next frame of the batch: "
                             f"set loop.batch_size >= 2 (it is {self.loop.batch_size}) or paste_prob = 0")


_FAST_MODEL = MaskRCNNConfig(
    depth=18, width=32, fpn_channels=64, input_hw=(240, 320), anchor_sizes=(8.0, 18.0, 40.0, 90.0, 200.0),
    rpn_pre_nms_train=1000, rpn_post_nms_train=500, rpn_pre_nms_test=500, rpn_post_nms_test=200,
    roi_batch_per_image=128, box_rep=256, mask_channels=64, pose_channels=64, pose_rep=256,
)
PRESETS: dict[str, PoseTrainConfig] = {
    "fast": PoseTrainConfig(model=_FAST_MODEL, loop=LoopConfig(steps=1500, batch_size=2, lr=1e-3, log_every=10,
                                                               checkpoint_every=100)),
    "balanced": PoseTrainConfig(
        model=dataclasses.replace(_FAST_MODEL, depth=34, width=64, fpn_channels=128, input_hw=(480, 640),
                                  anchor_sizes=(32.0, 64.0, 128.0, 256.0, 512.0), roi_batch_per_image=256,
                                  box_rep=512, mask_channels=128, pose_channels=128, pose_rep=512),
        loop=LoopConfig(steps=6000, batch_size=2, lr=5e-4, checkpoint_every=250)),
    "accurate": PoseTrainConfig(model=MaskRCNNConfig(depth=50), loop=LoopConfig(steps=20000, batch_size=4, lr=5e-4,
                                                                                checkpoint_every=500)),
}


@dataclass(frozen=True)
class PoseDataset:
    """Where a dataset's parts are: the BOP scene, the models folder and the frame ids per split."""

    scene_dir: Path
    models_dir: Path
    splits: dict[str, list[int]]


def locate_dataset(path: Path) -> PoseDataset:
    """The scene, models folder and split ids of a dataset root or a BOP scene (see :func:`cadalign.train.data.select`).

    Models are ``ROOT/models`` for a dataset root and ``SCENE/../../models`` for a bare scene (BOP layout).
    """
    train = select(path, "train")
    splits = {"train": list(train.ids)}
    for name in ("val", "test"):
        try:
            splits[name] = list(select(path, name).ids)
        except InputError:  # an empty held-out split: nothing to score
            splits[name] = []
    root = Path(path) if (Path(path) / "splits.json").is_file() else train.scene_dir.parent.parent
    models = root / "models"
    if not (models / "models_info.json").is_file():
        raise InputError(f"{models}/models_info.json is missing: the dataset has no CAD models for the pose loss")
    return PoseDataset(train.scene_dir, models, splits)


symmetry_from_bop = symmetry_from_entry
"""Kept name: see :func:`cadalign.cad.models_info.symmetry_from_entry`."""


def load_object_geometry(models_dir: Path, n_points: int, seed: int = 0) -> dict[int, ObjectGeometry]:
    """Surface samples (metres), diameters and symmetries of every BOP model in ``models_dir`` (files in mm)."""

    info = read_json(Path(models_dir) / "models_info.json")
    out = {}
    for key, entry in sorted(info.items(), key=lambda kv: int(kv[0])):
        path = Path(models_dir) / f"obj_{int(key):06d}.ply"
        if not path.is_file():
            raise InputError(f"{path} is missing but listed in models_info.json; rebuild the dataset's models/")
        mesh = trimesh.load(path, force="mesh", process=False)
        pts = np.asarray(trimesh.sample.sample_surface(mesh, n_points, seed=seed + int(key))[0], dtype=np.float64)
        out[int(key)] = ObjectGeometry(pts * MM_TO_M, float(entry["diameter"]) * MM_TO_M, symmetry_from_bop(entry))
    return out


def _resize_item(item: dict, hw: tuple[int, int]) -> dict:
    """Resize image, masks, boxes (from the resized masks) and K to ``hw``; drops instances that vanish."""
    h0, w0 = item["image"].shape[-2:]
    h, w = hw
    if (h0, w0) == (h, w):
        return item
    image = F.interpolate(item["image"][None], size=hw, mode="bilinear", align_corners=False, antialias=True)[0]
    masks = item["masks"]
    if len(masks):
        masks = F.interpolate(masks[:, None].float(), size=hw, mode="bilinear", align_corners=False,
                              antialias=True)[:, 0] >= 0.5
    keep = [i for i in range(len(masks)) if bool(masks[i].any())]
    boxes = [mask_bbox(masks[i].numpy()) for i in keep]
    K = torch.diag(torch.tensor([w / w0, h / h0, 1.0])) @ item["K"]
    sel = torch.tensor(keep, dtype=torch.int64)
    xyxy = torch.tensor([[x, y, x + bw, y + bh] for x, y, bw, bh in boxes], dtype=torch.float32).reshape(-1, 4)
    return {**item, "image": image, "masks": masks[sel] if len(masks) else masks, "boxes": xyxy,
            "labels": item["labels"][sel], "obj_ids": item["obj_ids"][sel], "R": item["R"][sel],
            "t": item["t"][sel], "K": K}


class ResizedDetectionDataset(Dataset):
    """:class:`DetectionPoseDataset` items resized to the network input, cached after the first read."""

    def __init__(self, scene_dir: Path, ids: list[int], hw: tuple[int, int]) -> None:
        self.base = DetectionPoseDataset(scene_dir, ids)
        self.hw = hw
        self._cache: dict[int, dict] = {}

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, i: int) -> dict:
        if i not in self._cache:
            self._cache[i] = _resize_item(self.base[i], self.hw)
        return self._cache[i]


def targets_from_batch(batch: dict) -> list[dict]:
    """Per-image target dicts from a :func:`detection_collate` batch."""
    keys = ("boxes", "labels", "masks", "R", "t", "K", "obj_ids")
    return [{k: batch[k][i] for k in keys} for i in range(len(batch["boxes"]))]


def make_step_fn(loss: PoseLoss) -> Callable[[nn.Module, dict], tuple[torch.Tensor, dict[str, float]]]:
    """The loop's ``step_fn``: the sum of the detector's and the pose losses; each part as a metric."""

    def step_fn(model: nn.Module, batch: dict) -> tuple[torch.Tensor, dict[str, float]]:
        losses = model(batch["image"], targets_from_batch(batch), pose_loss=loss)
        total = sum(losses.values())
        return total, {k: float(v.detach()) for k, v in losses.items()}

    return step_fn


def make_augment(cfg: AugmentConfig, crop_hw: tuple[int, int] | None = None, crop_object_prob: float = 0.8,
                 zoom_prob: float = 0.0, zoom_max: float = 2.0, input_hw: tuple[int, int] | None = None,
                 balance_classes: bool = False, rotate_prob: float = 0.0, rotate_max_deg: float = 30.0,
                 paste_prob: float = 0.0, paste_max: int = 3) -> Callable[[dict, torch.Generator], dict] | None:
    """The loop's ``augment``: random (pasted, rolled, zoomed) crops (when ``crop_hw``, ``zoom_prob``,
    ``rotate_prob`` or ``paste_prob``), then colour jitter.

    Zoom, roll or paste without ``crop_hw`` crops to ``input_hw`` (the whole image), which must then be given.
    """
    if (zoom_prob > 0 or rotate_prob > 0 or paste_prob > 0) and crop_hw is None:
        if input_hw is None:
            raise ValueError("zoom, roll or paste without crop_hw needs input_hw")
        crop_hw = input_hw
    if not cfg.enabled and crop_hw is None:
        return None

    def augment(batch: dict, g: torch.Generator) -> dict:
        if crop_hw is not None:
            batch = crop_batch(batch, g, tuple(crop_hw), object_prob=crop_object_prob, zoom_prob=zoom_prob,
                               zoom_max=zoom_max, balance_classes=balance_classes, rotate_prob=rotate_prob,
                               rotate_max_deg=rotate_max_deg, paste_prob=paste_prob, paste_max=paste_max)
        return {**batch, "image": colour_jitter(batch["image"], g, cfg)} if cfg.enabled else batch

    return augment


def extra_state(cfg: PoseTrainConfig, classes: tuple[str, ...]) -> dict:
    """The identity saved with each checkpoint (checked on resume and by ``load_pose_model``)."""
    return {"model": MODEL_KIND, "classes": list(classes), "model_config": cfg.model}


def run(cfg: PoseTrainConfig, dataset: Path, out_dir: Path, *, resume: bool = False, overwrite: bool = False,
        device: str = "cpu", progress: Callable[[int, int, dict[str, float]], None] | None = None) -> TrainResult:
    """Train on the dataset's train split, write ``train_config.json`` and score the held-out split.

    The run record is :func:`cadalign.train.common.write_run_record`'s, as for the dense trainers.

    Raises:
        ConfigError: ``out_dir`` holds a run (unless ``resume`` or ``overwrite``), or a run of another config
            is resumed.
        TrainingError: a resumed run's classes or model differ.
        InputError: the dataset or its models are missing.
    """
    ds = locate_dataset(dataset)
    train_ids = ds.splits.get("train") or []
    if not train_ids:
        raise InputError(f"{dataset}: the train split is empty; the dataset needs more frames")
    data = ResizedDetectionDataset(ds.scene_dir, train_ids, cfg.model.input_hw)
    classes = data.base.classes.names
    identity = extra_state(cfg, classes)
    write_run_record(Path(out_dir), "pose", cfg, identity,
                     {"dataset": str(dataset), "splits": {k: len(v) for k, v in ds.splits.items()},
                      "images": read_prep(ds.scene_dir)}, resume=resume, overwrite=overwrite)
    geometry = load_object_geometry(ds.models_dir, cfg.model_points, cfg.loop.seed)
    loss = PoseLoss(geometry, cfg.loss)
    torch.manual_seed(cfg.loop.seed)
    model = MaskRCNNPose(cfg.model, classes)
    augment = make_augment(cfg.augment, cfg.crop_hw, crop_object_prob=cfg.crop_object_prob, zoom_prob=cfg.zoom_prob,
                           zoom_max=cfg.zoom_max, input_hw=cfg.model.input_hw,
                           balance_classes=cfg.crop_balance_classes, rotate_prob=cfg.rotate_prob,
                           rotate_max_deg=cfg.rotate_max_deg, paste_prob=cfg.paste_prob, paste_max=cfg.paste_max)
    result = train_loop(model, make_step_fn(loss), data, cfg.loop, Path(out_dir), collate_fn=detection_collate,
                        augment=augment, resume=resume, device=device, progress=progress,
                        extra_state=identity)
    held_out = sorted((ds.splits.get("val") or []) + (ds.splits.get("test") or []))
    if held_out and not result.interrupted and is_main_rank():  # under DDP rank 0 scores and writes
        model.eval()
        report = evaluate(model, ds.scene_dir, held_out, ds.models_dir, cfg.eval_score_thresh)
        write_json(Path(out_dir) / "eval_heldout.json", report)
        log.info("held-out frames: %s", ", ".join(f"{k} {v:.4g}" if isinstance(v, float | int) else f"{k} {v}"
                                                   for k, v in report["summary"].items()))
        for name, st in report["stage_recall"].items():
            log.info("held-out %s (%d): found by an anchor %.2f, a proposal %.2f, the box head %.2f, a detection %.2f",
                     name, st["n"], st["anchor"], st["proposal"], st["head"], st["detection"])
    return result

"""The held-out score of a detection + pose model, written by ``cadalign train pose`` (``eval_heldout.json``).

Scoring is :func:`cadalign.eval.pose_eval.evaluate_scene`, the function behind ``cadalign eval pose`` and
``cadalign infer --gt``: detections are matched greedily by score to the same class at box IoU >= 0.5, GT
instances with ``visib_fract`` < 0.1 (and optionally smaller than ``min_box_side_px``) are don't-care, the
structure class is not scored, and rotation errors are minimised over the symmetries that ``models_info.json``
declares. The two reports therefore agree on the same poses (tests/pose/test_pose_eval_agree.py).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cadalign.data.torch_datasets import DetectionPoseDataset
from cadalign.eval.pose_eval import (
    CroppedMask,
    PoseEvalConfig,
    PosePrediction,
    evaluate_scene,
    load_bop_models,
)
from cadalign.models.maskrcnn.detector import MaskRCNNPose
from cadalign.types import Rigid3


def predict(model: MaskRCNNPose, dataset: DetectionPoseDataset, score_thresh: float = 0.5) -> list[PosePrediction]:
    """``model.detect`` on every frame of ``dataset`` as :class:`PosePrediction` (labels in the scene's classes)."""
    label_of = {n: i for i, n in enumerate(dataset.classes.names)}  # by name: the model's list may differ
    names = tuple(getattr(model, "classes", ()))
    out = []
    for i in range(len(dataset)):
        item = dataset[i]
        for d in model.detect(item["image"], item["K"], score_thresh):
            label = label_of.get(names[d.label], -1) if d.label < len(names) else d.label
            T = Rigid3(np.asarray(d.R_cam_from_obj, float), np.asarray(d.t_cam_from_obj_m, float).reshape(3))
            mask = CroppedMask.of(d.mask) if d.mask is not None else None
            out.append(PosePrediction(int(item["im_id"]), label, float(d.score), np.asarray(d.box_xyxy, float), T,
                                      None, mask))
    return out


def summary(report: dict) -> dict:
    """Flat overall numbers of an :func:`evaluate_scene` report: detection counts/P/R/F1, mean/median errors and
    mask IoU of the matches."""
    out = dict(report["detection"])
    for key in ("t_err_m", "r_err_deg", "mask_iou"):
        stats = report["overall"][key]
        out[f"{key}_mean"] = stats["mean"] if stats["n"] else None  # None (JSON null): no match to measure
        out[f"{key}_median"] = stats["median"] if stats["n"] else None
    return out


def evaluate(model: MaskRCNNPose, scene_dir: Path, ids: list[int], models_dir: Path, score_thresh: float = 0.5,
             cfg: PoseEvalConfig | None = None) -> dict:
    """Score ``model`` on frames ``ids`` of a BOP scene with the rules of ``cadalign eval pose``.

    Returns:
        the :func:`evaluate_scene` report without its per-match rows, plus ``summary`` (:func:`summary`),
        ``frames``, ``ids``, ``seconds_per_frame`` and ``score_thresh``.
    """
    dataset = DetectionPoseDataset(scene_dir, ids)
    t0 = time.perf_counter()
    preds = predict(model, dataset, score_thresh)
    seconds = (time.perf_counter() - t0) / max(len(ids), 1)
    report = evaluate_scene(preds, scene_dir, load_bop_models(models_dir), dataset.classes.names,
                            dataset.classes.class_of_obj, cfg or PoseEvalConfig(), list(ids))
    report.pop("matches")
    return {**report, "summary": summary(report), "frames": len(ids), "ids": list(ids),
            "seconds_per_frame": seconds, "score_thresh": score_thresh}

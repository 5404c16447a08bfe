"""The held-out score of a detection + pose model, written by ``cadalign train pose`` (``eval_heldout.json``).

Scoring is :func:`cadalign.metrics.pose_eval.evaluate_scene`, the function behind ``cadalign eval pose`` and
``cadalign infer --gt``: detections are matched greedily by score to the same class at box IoU >= 0.5, GT
instances with ``visib_fract`` < 0.1 (and optionally smaller than ``min_box_side_px``) are don't-care, the
structure class is not scored, and rotation errors are minimised over the symmetries that ``models_info.json``
declares. The two reports therefore agree on the same poses (tests/pose/test_pose_eval_agree.py).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from cadalign.metrics.pose_eval import (
    CroppedMask,
    PoseEvalConfig,
    PosePrediction,
    counted,
    evaluate_scene,
    gt_instances,
    load_bop_models,
)
from cadalign.models.maskrcnn.detector import MaskRCNNPose
from cadalign.models.ops import box_iou
from cadalign.train.datasets import DetectionPoseDataset
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


STAGES = ("anchor", "proposal", "head", "detection")
"""The detector's stages in :func:`stage_recall`'s order."""


def stage_recall(model: MaskRCNNPose, dataset: DetectionPoseDataset, preds: list[PosePrediction],
                 score_thresh: float = 0.5, cfg: PoseEvalConfig | None = None) -> dict[str, dict[str, float]]:
    """Where the detector loses each scored class: per class, of the ground-truth instances whose miss counts
    (``cadalign eval pose``'s rules), the fraction that still has, at box IoU >= ``cfg.iou_thresh``,

    - ``anchor``: an anchor (what the RPN can be trained to fire on: the anchor sizes, scales and ratios);
    - ``proposal``: an RPN proposal at inference;
    - ``head``: such a proposal that the box head gives the instance's class with probability >= ``score_thresh``;
    - ``detection``: a final detection of its class scoring >= ``score_thresh`` (``preds``).

    Each is "some box exists", not a one-to-one match, so ``detection`` bounds the recall from above. A drop
    from one stage to the next says which part to work on (anchors, the RPN, the box head's classes, or its
    regression and NMS). ``n`` is the number of instances; classes without any are left out.
    """
    cfg = cfg or PoseEvalConfig()
    names = dataset.classes.names
    model_col = {n: i for i, n in enumerate(getattr(model, "classes", ()))}
    scene = dataset.scene
    found: dict[int, list[list[bool]]] = {}
    by_frame: dict[int, list[PosePrediction]] = {}
    for p in preds:
        by_frame.setdefault(p.im_id, []).append(p)
    for i, im_id in enumerate(dataset.ids):
        gts = [g for g in gt_instances(scene, im_id, dataset.classes.class_of_obj)
               if names[g.label] not in cfg.ignore_classes and counted(g, cfg)]
        if not gts:
            continue
        st = model.stage_boxes(dataset.image(i))
        gt_boxes = torch.tensor(np.array([g.box_xyxy for g in gts]), dtype=torch.float32)
        gt_labels = torch.tensor([g.label for g in gts])
        near_anchor = (box_iou(gt_boxes, st["anchors"].float().cpu()) >= cfg.iou_thresh).any(1)
        near_prop = box_iou(gt_boxes, st["proposals"].float().cpu()) >= cfg.iou_thresh
        probs = st["proposal_probs"].cpu()
        dets = [p for p in by_frame.get(im_id, []) if p.score >= score_thresh]
        det_boxes = torch.tensor(np.array([p.box_xyxy for p in dets]).reshape(-1, 4), dtype=torch.float32)
        det_labels = torch.tensor([p.label for p in dets], dtype=torch.int64)
        near_det = ((box_iou(gt_boxes, det_boxes) >= cfg.iou_thresh)
                    & (gt_labels[:, None] == det_labels[None, :])).any(1)
        for j, g in enumerate(gts):
            col = model_col.get(names[g.label])
            head = bool(col is not None and (near_prop[j] & (probs[:, col] >= score_thresh)).any())
            found.setdefault(g.label, []).append([bool(near_anchor[j]), bool(near_prop[j].any()), head,
                                                  bool(near_det[j])])
    out = {}
    for label, rows in sorted(found.items()):
        frac = np.mean(np.array(rows, float), axis=0)
        out[names[label]] = {"n": len(rows), **{k: float(v) for k, v in zip(STAGES, frac, strict=True)}}
    return out


def evaluate(model: MaskRCNNPose, scene_dir: Path, ids: list[int], models_dir: Path, score_thresh: float = 0.5,
             cfg: PoseEvalConfig | None = None) -> dict:
    """Score ``model`` on frames ``ids`` of a BOP scene with the rules of ``cadalign eval pose``.

    Returns:
        the :func:`evaluate_scene` report without its per-match rows, plus ``summary`` (:func:`summary`),
        ``stage_recall`` (:func:`stage_recall`), ``frames``, ``ids``, ``seconds_per_frame`` and ``score_thresh``.
    """
    cfg = cfg or PoseEvalConfig()
    dataset = DetectionPoseDataset(scene_dir, ids)
    t0 = time.perf_counter()
    preds = predict(model, dataset, score_thresh)
    seconds = (time.perf_counter() - t0) / max(len(ids), 1)
    report = evaluate_scene(preds, scene_dir, load_bop_models(models_dir), dataset.classes.names,
                            dataset.classes.class_of_obj, cfg, list(ids))
    report.pop("matches")
    report.pop("misses")
    stages = stage_recall(model, dataset, preds, score_thresh, cfg)
    return {**report, "summary": summary(report), "stage_recall": stages, "frames": len(ids), "ids": list(ids),
            "seconds_per_frame": seconds, "score_thresh": score_thresh}

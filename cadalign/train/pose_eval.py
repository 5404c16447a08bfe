"""A quick held-out score of a detection + pose model, written by ``cadalign train pose`` (``eval_heldout.json``).

Detections are matched to ground truth of the same class greedily by decreasing score at box IoU >= 0.5
(each ground-truth instance at most once). Per class and overall: precision, recall, F1, mean mask IoU of the
matches, and their translation error (m) and rotation error (deg; minimum over the object's symmetries when
given). The full metric suite (ADD(-S), MSSD/MSPD, distance bins) is ``cadalign eval pose``.
"""

from __future__ import annotations

import time
from collections import defaultdict

import numpy as np
import torch
from torch.utils.data import Dataset

from cadalign.models.maskrcnn.detector import MaskRCNNPose
from cadalign.models.ops import box_iou


def _rot_err_deg(R_pred: np.ndarray, R_gt: np.ndarray, sym_R: list[np.ndarray]) -> float:
    errs = []
    for S in sym_R:
        M = R_pred.T @ (R_gt @ S)
        errs.append(np.degrees(np.arccos(np.clip((np.trace(M) - 1) / 2, -1.0, 1.0))))
    return float(min(errs))


def _summ(rows: dict[str, list[float]], tp: int, fp: int, fn: int) -> dict[str, float | None]:
    p = tp / (tp + fp) if tp + fp else 0.0
    r = tp / (tp + fn) if tp + fn else 0.0
    out = {"tp": tp, "fp": fp, "fn": fn, "precision": p, "recall": r, "f1": 2 * p * r / (p + r) if p + r else 0.0}
    for key, vals in rows.items():
        out[f"{key}_mean"] = float(np.mean(vals)) if vals else None  # None (JSON null): no match to measure
        out[f"{key}_median"] = float(np.median(vals)) if vals else None
    return out


def evaluate(model: MaskRCNNPose, dataset: Dataset, score_thresh: float = 0.5,
             symmetries: dict[int, list[np.ndarray]] | None = None) -> dict:
    """Score ``model.detect`` on every item of a detection dataset (items as ``DetectionPoseDataset``'s).

    Returns:
        ``{"summary": {...}, "per_class": {name: {...}}, "frames": n, "seconds_per_frame": s}``.
    """
    counts: dict[int, list[int]] = defaultdict(lambda: [0, 0, 0])
    errs: dict[int, dict[str, list[float]]] = defaultdict(lambda: {"t_err_m": [], "r_err_deg": [], "mask_iou": []})
    t0 = time.perf_counter()
    for i in range(len(dataset)):
        item = dataset[i]
        dets = model.detect(item["image"], item["K"], score_thresh)
        used = np.zeros(len(item["labels"]), dtype=bool)
        for d in dets:  # already by decreasing score
            c = counts[d.label]
            cand = np.flatnonzero((item["labels"].numpy() == d.label) & ~used)
            if len(cand) == 0:
                c[1] += 1
                continue
            ious = box_iou(torch.tensor(d.box_xyxy, dtype=torch.float32)[None], item["boxes"][cand])[0].numpy()
            j = int(np.argmax(ious))
            if ious[j] < 0.5:
                c[1] += 1
                continue
            g = int(cand[j])
            used[g] = True
            c[0] += 1
            gm = item["masks"][g].numpy()
            inter, union = np.logical_and(gm, d.mask).sum(), np.logical_or(gm, d.mask).sum()
            e = errs[d.label]
            e["mask_iou"].append(float(inter / union) if union else 0.0)
            e["t_err_m"].append(float(np.linalg.norm(d.t_cam_from_obj_m - item["t"][g].double().numpy())))
            sym = (symmetries or {}).get(int(item["obj_ids"][g]), [np.eye(3)])
            e["r_err_deg"].append(_rot_err_deg(d.R_cam_from_obj, item["R"][g].double().numpy(), sym))
        for g in np.flatnonzero(~used):
            counts[int(item["labels"][g])][2] += 1
    names = getattr(model, "classes", ())
    per_class = {names[k] if k < len(names) else str(k): _summ(errs[k], *counts[k]) for k in sorted(counts)}
    total = [sum(counts[k][j] for k in counts) for j in range(3)]
    pooled = {key: [v for k in errs for v in errs[k][key]] for key in ("t_err_m", "r_err_deg", "mask_iou")}
    n = len(dataset)
    return {"summary": _summ(pooled, *total), "per_class": per_class, "frames": n,
            "seconds_per_frame": (time.perf_counter() - t0) / max(n, 1), "score_thresh": score_thresh}

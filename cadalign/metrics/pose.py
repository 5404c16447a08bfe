"""6-DoF pose and detection metrics: box/mask IoU, matching, rotation/translation errors, ADD(-S), BOP MSSD/MSPD.

Definitions follow the BOP toolkit (https://github.com/thodan/bop_toolkit, ``bop_toolkit_lib/pose_error.py``
and ``scripts/eval_bop19_pose.py``):

- ADD: mean distance between model points under the estimated and the true pose; ADD-S (BOP's ``adi``):
  mean over the true-pose points of the distance to the nearest estimated-pose point.
- MSSD: ``min_S max_x |T_est x - T_gt S x|`` over the symmetry transforms ``S`` (metres);
  MSPD: the same in pixels after projection with ``K``.
- Continuous symmetries are discretised as BOP does with ``max_sym_disc_step = 0.01``:
  ``ceil(pi / 0.01) = 315`` rotations (we keep the identity, which BOP's loop starts after).
- Recall thresholds (BOP19): MSSD ``e < th * diameter`` for ``th = 0.05, 0.10, ..., 0.50``; MSPD
  ``e < th * w / 640`` px for ``th = 5, 10, ..., 50``; the average recall is the mean over thresholds.

Rotation error is the geodesic angle minimised over the symmetry group; for a continuous symmetry about
axis ``a`` the minimum over the circle is exact: ``arccos(a . (R_gt^T R_est D^T) a)`` (the smallest
rotation between ``a`` and its image), so no discretisation error enters it. Boxes are ``x0, y0, x1, y1``
in pixels with ``x1``/``y1`` exclusive (pixel-edge coordinates of :mod:`cadalign.types`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from cadalign.cad.symmetry import Symmetry
from cadalign.geometry.camera import project_points
from cadalign.geometry.compare import box_iou as box_iou
from cadalign.geometry.compare import mask_iou as mask_iou
from cadalign.geometry.rotations import geodesic_angle

MSSD_THRESHOLDS = tuple(round(0.05 * k, 2) for k in range(1, 11))
"""BOP19 MSSD thresholds as fractions of the object diameter."""
MSPD_THRESHOLDS_PX = tuple(5.0 * k for k in range(1, 11))
"""BOP19 MSPD thresholds in pixels at 640 px image width (scaled by ``width / 640``)."""
BOP_SYM_DISC_STEP = 0.01
"""BOP's ``max_sym_disc_step`` for discretising continuous symmetries."""


def match_detections(
    pred_boxes: np.ndarray, pred_labels: np.ndarray, pred_scores: np.ndarray,
    gt_boxes: np.ndarray, gt_labels: np.ndarray, iou_thresh: float = 0.5,
) -> list[tuple[int, int]]:
    """Greedy one-to-one matching by descending score, same class, box IoU >= ``iou_thresh`` (COCO style).

    Returns:
        ``(pred_index, gt_index)`` pairs; each prediction takes the free GT box of its class with the
        highest IoU.
    """
    iou = box_iou(pred_boxes, gt_boxes)
    gt_labels = np.asarray(gt_labels)
    taken = np.zeros(len(gt_labels), dtype=bool)
    pairs = []
    for i in np.argsort(-np.asarray(pred_scores, dtype=np.float64), kind="stable"):
        ok = (gt_labels == pred_labels[i]) & ~taken & (iou[i] >= iou_thresh) if len(gt_labels) else taken
        if not np.any(ok):
            continue
        j = int(np.argmax(np.where(ok, iou[i], -1.0)))
        taken[j] = True
        pairs.append((int(i), j))
    return pairs


@dataclass(frozen=True)
class DetectionCounts:
    """True/false positives and misses of one class (or of all)."""

    tp: int
    fp: int
    fn: int

    @property
    def precision(self) -> float:
        return self.tp / (self.tp + self.fp) if self.tp + self.fp else 0.0

    @property
    def recall(self) -> float:
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else 0.0

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        return 2 * p * r / (p + r) if p + r else 0.0

    def as_dict(self) -> dict:
        return {"tp": self.tp, "fp": self.fp, "fn": self.fn, "precision": self.precision,
                "recall": self.recall, "f1": self.f1}


FP_KINDS = ("class", "duplicate", "localization", "both", "background")
"""Why a prediction is a false positive (TIDE, Bolya et al. 2020), in the order they are tested: it overlaps a
target of another class by the match IoU (``class``); its own class's target, taken by a better-scoring one
(``duplicate``); a target of its class by less than the match IoU but at least the background IoU
(``localization``); another class's target so (``both``); nothing (``background``)."""
FN_KINDS = ("localization", "class", "missed")
"""Why a target is missed: a false positive of its class covers it poorly (``localization``), one of another class
covers it well (``class``), or no prediction does (``missed``)."""


@dataclass(frozen=True)
class FrameErrors:
    """The error kinds of one frame's unmatched predictions and missed targets (see :func:`detection_errors`)."""

    fp_kind: list[str | None]
    """Per prediction: its :data:`FP_KINDS` entry, None when matched."""
    fn_kind: list[str | None]
    """Per target: its :data:`FN_KINDS` entry, None when matched or not counted."""
    fixed_by: list[int | None]
    """Per target: the false positive that would match it were its error fixed (a ``localization`` or ``class``
    false positive paired one to one, best-scoring first), else None."""


def detection_errors(pred_boxes: np.ndarray, pred_labels: np.ndarray, pred_scores: np.ndarray, gt_boxes: np.ndarray,
                     gt_labels: np.ndarray, gt_counted: np.ndarray, pairs: list[tuple[int, int]],
                     iou_thresh: float = 0.5, bg_iou: float = 0.1) -> FrameErrors:
    """Sort one frame's detection errors into TIDE's kinds (:data:`FP_KINDS`, :data:`FN_KINDS`).

    ``pairs`` is :func:`match_detections`' answer for the same boxes; ``gt_counted`` (G,) bool marks the targets
    whose miss counts (BOP's "don't care" ones are False). A miss is explained by a ``localization`` or
    ``class`` false positive only when that one can be paired with it one to one (by descending score, the
    highest IoU first), so that fixing the error would turn exactly that false positive into a true positive.
    """
    pl, gl = np.asarray(pred_labels), np.asarray(gt_labels)
    n, g = len(pl), len(gl)
    iou = box_iou(pred_boxes, gt_boxes)  # (n, g), empty sides included
    same = pl[:, None] == gl[None, :]
    matched_p, matched_g = {i for i, _ in pairs}, {j for _, j in pairs}
    fp_kind: list[str | None] = [None] * n
    for i in range(n):
        if i in matched_p:
            continue
        best_same = float(np.max(iou[i], initial=0.0, where=same[i]))
        best_other = float(np.max(iou[i], initial=0.0, where=~same[i]))
        fp_kind[i] = ("class" if best_other >= iou_thresh else "duplicate" if best_same >= iou_thresh else
                      "localization" if best_same >= bg_iou else "both" if best_other >= bg_iou else "background")
    missing = [j for j in range(g) if j not in matched_g and bool(gt_counted[j])]
    fixed_by: list[int | None] = [None] * g
    for kind, rel, lo, hi in (("localization", same, bg_iou, iou_thresh), ("class", ~same, iou_thresh, np.inf)):
        for i in np.argsort(-np.asarray(pred_scores, dtype=np.float64), kind="stable"):
            if fp_kind[i] != kind:
                continue
            free = [j for j in missing if fixed_by[j] is None and rel[i, j] and lo <= iou[i, j] < hi]
            if free:
                fixed_by[max(free, key=lambda j: iou[i, j])] = int(i)
    fn_kind: list[str | None] = [None] * g
    for j in missing:
        fn_kind[j] = "missed" if fixed_by[j] is None else fp_kind[fixed_by[j]]
    return FrameErrors(fp_kind, fn_kind, fixed_by)


def symmetry_transforms(symmetry: Symmetry | None, diameter_m: float | None = None) -> list[np.ndarray]:
    """The (4, 4) symmetry transforms used by MSSD/MSPD/ADD: identity first; continuous ones discretised as BOP.

    ``diameter_m`` is accepted for interface clarity only: BOP's step count ``ceil(pi / 0.01)`` does not
    depend on it.
    """
    del diameter_m
    if symmetry is None or symmetry.kind == "none":
        return [np.eye(4)]
    return symmetry.discretize(int(math.ceil(math.pi / BOP_SYM_DISC_STEP)))


def rotation_error_deg(R_est: np.ndarray, R_gt: np.ndarray, symmetry: Symmetry | None = None) -> float:
    """Geodesic angle (degrees) between two (3, 3) rotations, minimised over the object's symmetries."""
    R_est, R_gt = np.asarray(R_est, float), np.asarray(R_gt, float)
    sym = symmetry if symmetry is not None else Symmetry.none()
    D = np.stack([np.eye(3), *(d[:3, :3] for d in sym.discrete)])
    if sym.kind == "continuous":  # the angle between the axis and its image: the spin about it is free
        a = np.asarray(sym.axis, float)
        N = R_gt.T @ R_est @ np.swapaxes(D, 1, 2)
        best = math.acos(float(np.clip(np.einsum("i,nij,j->n", a, N, a).max(), -1.0, 1.0)))
    else:
        best = float(geodesic_angle(R_gt, R_est @ np.swapaxes(D, 1, 2)).min())
    return math.degrees(best)


def translation_error_m(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    """Euclidean distance (metres) between two translations (3,)."""
    return float(np.linalg.norm(np.asarray(t_est, float) - np.asarray(t_gt, float)))


def _apply(R: np.ndarray, t: np.ndarray, pts: np.ndarray) -> np.ndarray:
    return pts @ np.asarray(R, float).T + np.asarray(t, float)


def add(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD: mean distance (m) of model points (N, 3) under the estimated and the true pose."""
    return float(np.linalg.norm(_apply(R_est, t_est, pts) - _apply(R_gt, t_gt, pts), axis=1).mean())


def add_s(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray) -> float:
    """ADD-S (BOP ``adi``): mean over true-pose points of the distance to the nearest estimated-pose point."""
    d, _ = cKDTree(_apply(R_est, t_est, pts)).query(_apply(R_gt, t_gt, pts), k=1)
    return float(np.mean(d))


def mssd(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, pts: np.ndarray,
         syms: list[np.ndarray]) -> float:
    """Maximum Symmetry-aware Surface Distance (m): ``min_S max_x |T_est x - T_gt S x|``."""
    pe = _apply(R_est, t_est, pts)
    return min(float(np.linalg.norm(pe - _apply(R_gt @ S[:3, :3], R_gt @ S[:3, 3] + t_gt, pts), axis=1).max())
               for S in syms)


def mspd(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray, K: np.ndarray,
         pts: np.ndarray, syms: list[np.ndarray]) -> float:
    """Maximum Symmetry-aware Projection Distance (px): MSSD's max after projection with ``K`` (3, 3)."""
    pe = project_points(K, _apply(R_est, t_est, pts), signed=True)
    return min(float(np.linalg.norm(pe - project_points(K, _apply(R_gt @ S[:3, :3], R_gt @ S[:3, 3] + t_gt, pts),
                                    signed=True), axis=1).max()) for S in syms)


def recall_curve(errors: np.ndarray, n_targets: int, thresholds: np.ndarray) -> np.ndarray:
    """Recall per threshold: the fraction of ``n_targets`` whose error is strictly below it (NaN/inf fail)."""
    e = np.asarray(errors, dtype=np.float64)
    e = e[np.isfinite(e)]
    if n_targets <= 0:
        return np.full(len(thresholds), np.nan)
    return np.array([np.count_nonzero(e < th) / n_targets for th in thresholds])


def mssd_thresholds_m(diameter_m: float) -> np.ndarray:
    """BOP19 MSSD thresholds in metres for an object of diameter ``diameter_m``."""
    return np.asarray(MSSD_THRESHOLDS) * diameter_m


def mspd_thresholds_px(image_width: int) -> np.ndarray:
    """BOP19 MSPD thresholds in pixels for an image ``image_width`` pixels wide."""
    return np.asarray(MSPD_THRESHOLDS_PX) * image_width / 640.0


def error_stats(values: np.ndarray) -> dict[str, float]:
    """``min/max/mean/std/median`` and ``n`` of the finite values (thesis Table 4.5 layout); NaN when empty."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return {"n": 0, "min": math.nan, "max": math.nan, "mean": math.nan, "std": math.nan, "median": math.nan}
    return {"n": int(len(v)), "min": float(v.min()), "max": float(v.max()), "mean": float(v.mean()),
            "std": float(v.std()), "median": float(np.median(v))}


def binned_by(values: dict[str, np.ndarray], key: np.ndarray, edges: tuple[float, ...]) -> list[dict]:
    """Mean and median of each error array in ``values`` per bin of ``key`` (e.g. camera distance, m).

    Bins are ``[edges[i], edges[i + 1])``; empty bins are kept with ``n = 0``.
    """
    key = np.asarray(key, dtype=np.float64)
    rows = []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (key >= lo) & (key < hi)
        row: dict = {"lo": float(lo), "hi": float(hi), "n": int(sel.sum())}
        for name, v in values.items():
            vv = np.asarray(v, dtype=np.float64)[sel]
            vv = vv[np.isfinite(vv)]
            row[f"{name}_mean"] = float(vv.mean()) if len(vv) else math.nan
            row[f"{name}_median"] = float(np.median(vv)) if len(vv) else math.nan
        rows.append(row)
    return rows

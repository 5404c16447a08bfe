"""Dataset-level pose evaluation against a BOP scene: detection P/R/F1, pose errors, BOP recalls, tables.

Predictions (:class:`PosePrediction`) are matched per frame to the ground-truth instances with visible
pixels (greedy by score, same class, box IoU >= ``iou_thresh``). GT instances with ``visib_fract`` below
``min_visib_fract`` are "don't care" (BOP's convention): missing them is no miss, and a prediction matched
to one is neither a hit nor a false positive. Pose errors are computed for matched pairs; recalls
(ADD(-S) < 0.1 d, BOP MSSD and MSPD averages) count every target, unmatched ones as failures.

Each class's ``errors`` say why its F1 is what it is: its false positives and misses sorted into TIDE's kinds
(Bolya et al., ECCV 2020; :func:`~cadalign.metrics.pose.detection_errors`) and the F1 were every error of one
kind fixed. On the default orbit's 33 held-out frames (session 19's 4200-step ``improved`` network, ``infer
--preset accurate``) hot stab F1 0.367 would be 0.603 with the localization errors fixed (boxes on a hot stab's
handle alone) and 0.748 with the misses no box came near; valve F1 0.817 would be 0.953 without the misses.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from cadalign.cad.models_info import symmetry_from_entry
from cadalign.cad.symmetry import Symmetry
from cadalign.errors import InputError
from cadalign.formats.bop import BopScene, mask_bbox
from cadalign.io import read_json
from cadalign.metrics import pose as pm
from cadalign.types import Rigid3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvalModel:
    """A model as the metrics see it: points (N, 3) in metres (model frame), diameter and symmetry."""

    points_m: np.ndarray
    diameter_m: float
    symmetry: Symmetry = field(default_factory=Symmetry.none)


@dataclass(frozen=True)
class CroppedMask:
    """A boolean mask stored as its bounding-box crop (long videos would not fit as full frames)."""

    crop: np.ndarray
    x0: int
    y0: int

    @staticmethod
    def of(mask: np.ndarray) -> CroppedMask:
        m = np.asarray(mask, bool)
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        if len(rows) == 0:
            return CroppedMask(np.zeros((0, 0), bool), 0, 0)
        return CroppedMask(m[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1].copy(), int(cols[0]), int(rows[0]))

    def full(self, shape: tuple[int, int]) -> np.ndarray:
        out = np.zeros(shape, bool)
        h, w = self.crop.shape
        out[self.y0:self.y0 + h, self.x0:self.x0 + w] = self.crop[: shape[0] - self.y0, : shape[1] - self.x0]
        return out


@dataclass(frozen=True)
class PosePrediction:
    """One predicted instance in one frame (metres, pixels)."""

    im_id: int
    label: int
    """Class index (the scene's ``objects.json`` class list)."""
    score: float
    box_xyxy: np.ndarray
    T_cam_from_obj: Rigid3
    obj_id: int | None = None
    """BOP model id when the pipeline identified it; else the matched GT instance's model is used."""
    mask: np.ndarray | CroppedMask | None = None


@dataclass(frozen=True)
class PoseEvalConfig:
    iou_thresh: float = 0.5
    """Box IoU for a detection to count as a hit."""
    min_visib_fract: float = 0.1
    """GT instances less visible than this are "don't care" (BOP uses 0.1)."""
    min_box_side_px: float = 0.0
    """GT instances whose visible box's shorter side is below this (px) are "don't care" too (0 = off). The
    default scene's two smallest valves (87 and 145 mm) are 1-4 px at 640x480 and fully visible, so
    ``visib_fract`` keeps them as targets no detector can hit; a COCO-style size cut says so explicitly."""
    ignore_classes: tuple[str, ...] = ("background", "structure")
    """Classes not evaluated (the structure is the frame the parts sit on, not a detection target)."""
    distance_bins_m: tuple[float, ...] = (0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 15.0, 20.0, math.inf)
    """Edges of the camera-distance bins (m) of the binned errors."""


def load_bop_models(models_dir: Path, *, max_points: int = 20000) -> dict[int, EvalModel]:
    """``models_dir/obj_XXXXXX.ply`` (mm) + ``models_info.json`` -> obj_id -> :class:`EvalModel` (metres).

    Uses the mesh vertices as the metric's points (as BOP does), subsampled evenly to ``max_points``.
    """

    models_dir = Path(models_dir)
    info = read_json(models_dir / "models_info.json")
    out = {}
    for key, entry in info.items():
        ply = models_dir / f"obj_{int(key):06d}.ply"
        if not ply.is_file():
            raise InputError(f"{ply} is missing but listed in {models_dir / 'models_info.json'}")
        pts = np.asarray(trimesh.load(ply, process=False).vertices, dtype=np.float64) / 1000.0
        if len(pts) > max_points:
            pts = pts[np.linspace(0, len(pts) - 1, max_points).astype(int)]
        out[int(key)] = EvalModel(pts, float(entry["diameter"]) / 1000.0, symmetry_from_entry(entry))
    return out


@dataclass(frozen=True)
class GtInstance:
    im_id: int
    gt_idx: int
    obj_id: int
    label: int
    box_xyxy: np.ndarray
    T_cam_from_obj: Rigid3
    visib_fract: float
    mask: np.ndarray | None


def gt_instances(scene: BopScene, im_id: int, class_of_obj: dict[int, int], *, masks: bool = True) -> list[GtInstance]:
    """The frame's GT instances with visible pixels (box from the visible mask, xyxy exclusive)."""
    frame = scene.frame(im_id)
    out = []
    for g, inst in enumerate(frame.instances):
        info = frame.info[g] if g < len(frame.info) else {}
        m = scene.mask(im_id, g, visible=True) if masks or not info else None
        if m is not None:
            x, y, w, h = mask_bbox(m)
        else:
            x, y, w, h = info["bbox_visib"]
        if w <= 0 or h <= 0:
            continue
        vf = float(info.get("visib_fract", 1.0))
        out.append(GtInstance(im_id, g, inst.obj_id, class_of_obj[inst.obj_id], np.array([x, y, x + w, y + h], float),
                              inst.T_cam_from_obj, vf, m))
    return out


def _mask_iou(pred: np.ndarray | CroppedMask | None, gt: np.ndarray | None) -> float:
    if pred is None or gt is None:
        return math.nan
    return pm.mask_iou(pred.full(gt.shape) if isinstance(pred, CroppedMask) else pred, gt)


def _pose_row(p: PosePrediction, g: GtInstance, model: EvalModel, K: np.ndarray, width: int) -> dict:
    Te, Tg = p.T_cam_from_obj, g.T_cam_from_obj
    syms = pm.symmetry_transforms(model.symmetry)
    sym = model.symmetry.kind != "none"
    pts = model.points_m
    return {
        "im_id": g.im_id, "gt_idx": g.gt_idx, "obj_id": g.obj_id, "label": g.label, "score": p.score,
        "pred_obj_id": p.obj_id, "distance_m": float(np.linalg.norm(Tg.t)), "visib_fract": g.visib_fract,
        "box_iou": float(pm.box_iou(p.box_xyxy[None], g.box_xyxy[None])[0, 0]),
        "mask_iou": _mask_iou(p.mask, g.mask),
        "t_err_m": pm.translation_error_m(Te.t, Tg.t),
        "r_err_deg": pm.rotation_error_deg(Te.R, Tg.R, model.symmetry),
        "add_m": pm.add(Te.R, Te.t, Tg.R, Tg.t, pts),
        "adds_m": pm.add_s(Te.R, Te.t, Tg.R, Tg.t, pts),
        "add_or_adds_m": pm.add_s(Te.R, Te.t, Tg.R, Tg.t, pts) if sym else pm.add(Te.R, Te.t, Tg.R, Tg.t, pts),
        "mssd_m": pm.mssd(Te.R, Te.t, Tg.R, Tg.t, pts, syms),
        "mspd_px": pm.mspd(Te.R, Te.t, Tg.R, Tg.t, K, pts, syms),
        "diameter_m": model.diameter_m, "image_width": width,
    }


def evaluate_scene(preds: list[PosePrediction], scene_dir: Path, models: dict[int, EvalModel],
                   class_names: tuple[str, ...], class_of_obj: dict[int, int], cfg: PoseEvalConfig,
                   im_ids: list[int] | None = None) -> dict:
    """Evaluate predictions against one BOP scene; returns the JSON-ready report (see :func:`summarise`)."""
    scene = BopScene(scene_dir)
    ids = sorted({p.im_id for p in preds} if im_ids is None else im_ids)
    keep = {c for c, n in enumerate(class_names) if n not in cfg.ignore_classes}
    counts = {c: [0, 0, 0] for c in keep}
    errors = _ErrorTally(keep)
    rows: list[dict] = []
    targets: list[dict] = []
    misses: list[dict] = []  # the counted targets nothing matched
    by_frame: dict[int, list[PosePrediction]] = {}
    for p in preds:
        if p.label in keep:
            by_frame.setdefault(p.im_id, []).append(p)
    for im_id in ids:
        frame = scene.frame(im_id)
        gts = [g for g in gt_instances(scene, im_id, class_of_obj) if g.label in keep]
        ps = by_frame.get(im_id, [])
        boxes = (np.array([p.box_xyxy for p in ps]).reshape(-1, 4), np.array([p.label for p in ps]),
                 np.array([p.score for p in ps]), np.array([g.box_xyxy for g in gts]).reshape(-1, 4),
                 np.array([g.label for g in gts]))
        pairs = pm.match_detections(*boxes, cfg.iou_thresh)
        matched_p = {i for i, _ in pairs}
        matched_g = {j: i for i, j in pairs}
        for i, p in enumerate(ps):
            if i not in matched_p:
                counts[p.label][1] += 1
        cares = [counted(g, cfg) for g in gts]
        errors.add(ps, gts, pm.detection_errors(*boxes, np.array(cares, bool), pairs, cfg.iou_thresh))
        for j, g in enumerate(gts):
            care = cares[j]
            row = None
            if j in matched_g:
                row = _pose_row(ps[matched_g[j]], g, models[g.obj_id], frame.camera.K, frame.camera.width)
                if care:
                    counts[g.label][0] += 1
                    rows.append(row)
            elif care:
                counts[g.label][2] += 1
                misses.append({"im_id": im_id, "gt_idx": g.gt_idx, "obj_id": g.obj_id, "label": g.label,
                               "visib_fract": float(g.visib_fract), "box_xyxy": [float(v) for v in g.box_xyxy]})
            if care:
                targets.append({"label": g.label, "obj_id": g.obj_id, "row": row,
                                "diameter_m": models[g.obj_id].diameter_m, "width": frame.camera.width})
    return {**summarise(rows, targets, counts, class_names, cfg, errors), "misses": misses}


def counted(g: GtInstance, cfg: PoseEvalConfig) -> bool:
    """Whether a target's miss counts (not BOP's "don't care": visible enough, and not below the size cut)."""
    side = min(g.box_xyxy[2] - g.box_xyxy[0], g.box_xyxy[3] - g.box_xyxy[1])
    return g.visib_fract >= cfg.min_visib_fract and side >= cfg.min_box_side_px


class _ErrorTally:
    """Per class: the kinds of false positives and misses (:func:`~cadalign.metrics.pose.detection_errors`).
    A miss of kind ``localization`` / ``class`` is one that fixing those false positives turns into a hit."""

    def __init__(self, classes: set[int]) -> None:
        self.fp = {c: dict.fromkeys(pm.FP_KINDS, 0) for c in classes}
        self.fn = {c: dict.fromkeys(pm.FN_KINDS, 0) for c in classes}

    def add(self, ps: list[PosePrediction], gts: list[GtInstance], fe: pm.FrameErrors) -> None:
        for p, kind in zip(ps, fe.fp_kind, strict=True):
            if kind is not None:
                self.fp[p.label][kind] += 1
        for g, kind in zip(gts, fe.fn_kind, strict=True):
            if kind is not None:
                self.fn[g.label][kind] += 1

    def summary(self, c: int, tp: int, fp: int, fn: int) -> dict:
        """``fp`` / ``fn``: counts per kind; ``f1_fixed``: the class's F1 were every error of a kind fixed (its false
        positives gone, the misses it explains hit; TIDE's "fixed" oracle, with F1 for AP)."""
        fixed = {}
        for kind in pm.FP_KINDS + ("missed",):
            gone, hit = self.fp[c].get(kind, 0), self.fn[c].get(kind, 0)
            fixed[kind] = pm.DetectionCounts(tp + hit, fp - gone, fn - hit).f1
        return {"fp": dict(self.fp[c]), "fn": dict(self.fn[c]), "f1_fixed": fixed}


def _recalls(targets: list[dict]) -> dict[str, float]:
    n = len(targets)
    if n == 0:
        return {"n_targets": 0, "ar_mssd": math.nan, "ar_mspd": math.nan, "add_s_01d": math.nan}
    mssd_ok, mspd_ok = np.zeros(len(pm.MSSD_THRESHOLDS)), np.zeros(len(pm.MSPD_THRESHOLDS_PX))
    add_ok = 0
    for t in targets:
        r = t["row"]
        if r is None:
            continue
        mssd_ok += r["mssd_m"] < pm.mssd_thresholds_m(t["diameter_m"])
        mspd_ok += r["mspd_px"] < pm.mspd_thresholds_px(t["width"])
        add_ok += r["add_or_adds_m"] < 0.1 * t["diameter_m"]
    return {"n_targets": n, "ar_mssd": float((mssd_ok / n).mean()), "ar_mspd": float((mspd_ok / n).mean()),
            "add_s_01d": add_ok / n, "mssd_recall": (mssd_ok / n).tolist(), "mspd_recall": (mspd_ok / n).tolist()}


def _model_id(rows: list[dict]) -> dict:
    """How many matched detections the pipeline gave a model id (``n``), how many of them the GT instance's
    model (``right``), and the t/R errors of those ``right`` ones: for a class with several CAD models (valve
    types, two hot stabs) a pose of the wrong model is off whatever its accuracy."""
    named = [r for r in rows if r.get("pred_obj_id") is not None]
    ok = [r for r in named if r["pred_obj_id"] == r["obj_id"]]
    return {"n": len(named), "right": len(ok),
            "t_err_m_right": pm.error_stats(np.array([r["t_err_m"] for r in ok])),
            "r_err_deg_right": pm.error_stats(np.array([r["r_err_deg"] for r in ok]))}


def summarise(rows: list[dict], targets: list[dict], counts: dict[int, list[int]], class_names: tuple[str, ...],
              cfg: PoseEvalConfig, errors: _ErrorTally | None = None) -> dict:
    """Detection per class (with its error kinds when ``errors`` is given), Table 4.5 (min/max/mean/std of t/R
    errors per class), recalls, distance bins."""
    per_class = {}
    for c, (tp, fp, fn) in sorted(counts.items()):
        cr = [r for r in rows if r["label"] == c]
        ct = [t for t in targets if t["label"] == c]
        per_class[class_names[c]] = {
            "detection": pm.DetectionCounts(tp, fp, fn).as_dict(),
            "t_err_m": pm.error_stats(np.array([r["t_err_m"] for r in cr])),
            "r_err_deg": pm.error_stats(np.array([r["r_err_deg"] for r in cr])),
            "mask_iou": pm.error_stats(np.array([r["mask_iou"] for r in cr])),
            "model_id": _model_id(cr),
            **_recalls(ct),
        }
        if errors is not None:
            per_class[class_names[c]]["errors"] = errors.summary(c, tp, fp, fn)
    tot = np.array(list(counts.values())).reshape(-1, 3).sum(0)
    errs = {k: np.array([r[k] for r in rows]) for k in ("t_err_m", "r_err_deg", "add_or_adds_m", "mspd_px",
                                                         "mask_iou")}
    return {
        "config": {"iou_thresh": cfg.iou_thresh, "min_visib_fract": cfg.min_visib_fract,
                   "min_box_side_px": cfg.min_box_side_px},
        "detection": pm.DetectionCounts(*map(int, tot)).as_dict(),
        "per_class": per_class,
        "overall": {"t_err_m": pm.error_stats(errs["t_err_m"]), "r_err_deg": pm.error_stats(errs["r_err_deg"]),
                    "mask_iou": pm.error_stats(errs["mask_iou"]), **_recalls(targets)},
        "by_distance": pm.binned_by(errs, np.array([r["distance_m"] for r in rows]), cfg.distance_bins_m),
        "matches": rows,
    }


def table_markdown(report: dict) -> str:
    """The thesis Table 4.5 layout (per class: detection F1, t/R error min/max/mean/std) plus BOP recalls, and
    the model identification: right model of those identified, and the mean t/R errors of the right ones."""
    head = ("| class | n | F1 | t min | t max | t mean | t std (m) | R min | R max | R mean | R std (deg) "
            "| AR_MSSD | AR_MSPD | ADD(-S)<0.1d | right model | t / R mean, right model |")
    lines = [head, "|" + "---|" * 16]
    for name, c in report["per_class"].items():
        t, r = c["t_err_m"], c["r_err_deg"]
        ident = c.get("model_id", {"n": 0})
        right = (f"{ident['right']}/{ident['n']} | {ident['t_err_m_right']['mean']:.3f} m / "
                 f"{ident['r_err_deg_right']['mean']:.2f} deg") if ident["n"] else "- | -"
        lines.append(f"| {name} | {t['n']} | {c['detection']['f1']:.3f} | " + " | ".join(
            f"{v:.3f}" for v in (t["min"], t["max"], t["mean"], t["std"])) + " | " + " | ".join(
            f"{v:.2f}" for v in (r["min"], r["max"], r["mean"], r["std"])) +
            f" | {c['ar_mssd']:.3f} | {c['ar_mspd']:.3f} | {c['add_s_01d']:.3f} | {right} |")
    errs = [(name, c["errors"], c["detection"]["f1"]) for name, c in report["per_class"].items() if "errors" in c]
    if errs:
        lines += ["", "Detection errors (TIDE's kinds: FP class / duplicate / localization / both / background; missed "
                  "targets explained by a localization or class FP, or missed), and each class's F1 were every "
                  "error of one kind fixed:", "",
                  "| class | F1 | FP cls / dup / loc / both / bkg | FN loc / cls / missed | F1 fixed: cls | dup | loc "
                  "| both | bkg | missed |", "|" + "---|" * 10]
        for name, e, f1 in errs:
            fx = e["f1_fixed"]
            lines.append(f"| {name} | {f1:.3f} | " + " / ".join(str(e["fp"][k]) for k in pm.FP_KINDS) + " | "
                         + " / ".join(str(e["fn"][k]) for k in pm.FN_KINDS) + " | "
                         + " | ".join(f"{fx[k]:.3f}" for k in pm.FP_KINDS + ("missed",)) + " |")
    return "\n".join(lines) + "\n"

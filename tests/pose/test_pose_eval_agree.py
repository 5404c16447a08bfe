"""``eval_heldout.json`` (train pose) and ``cadalign eval pose`` / ``infer --gt`` score the same poses alike."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cadalign.data.torch_datasets import DetectionPoseDataset
from cadalign.eval.pose_eval import gt_instances
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.detect import frame_ids
from cadalign.infer.pipeline import PoseRecord
from cadalign.infer.run import evaluate_run
from cadalign.train.pose_eval import evaluate
from cadalign.types import Detection, Rigid3

T_ERR_M = 0.05
R_ERR_DEG = 10.0


class _GtModel:
    """A stand-in detector: every visible GT instance, its pose moved by exactly 5 cm / 10 deg, plus one
    false positive per frame; frames are answered in the order they are asked for."""

    def __init__(self, scene: Path, ids: list[int]) -> None:
        ds = DetectionPoseDataset(scene, ids)
        self.classes = ds.classes.names
        self.frames = [self._frame(ds[i]) for i in range(len(ds))]
        self.calls = 0

    @staticmethod
    def _frame(item: dict) -> list[Detection]:
        dets = []
        for g in range(len(item["labels"])):
            R = axis_angle_to_matrix(np.array([0.0, np.radians(R_ERR_DEG), 0.0])) @ item["R"][g].double().numpy()
            t = item["t"][g].double().numpy() + np.array([T_ERR_M, 0.0, 0.0])
            dets.append(Detection(item["boxes"][g].numpy().astype(float), int(item["labels"][g]), 0.9 - 0.01 * g,
                                  item["masks"][g].numpy(), R, t))
        h, w = item["image"].shape[-2:]
        label = int(max(item["labels"])) if len(item["labels"]) else 1
        fp_mask = np.zeros((h, w), bool)
        fp_mask[:2, :2] = True  # a 2 px box in the corner: matches nothing
        dets.append(Detection(np.array([0.0, 0.0, 2.0, 2.0]), label, 0.1, fp_mask, np.eye(3), np.array([0, 0, 5.0])))
        return dets

    def detect(self, image, K, score_thresh: float = 0.5) -> list[Detection]:
        dets = [d for d in self.frames[self.calls] if d.score >= score_thresh]
        self.calls += 1
        return dets


def _records(model: _GtModel, scene: Path, ids: list[int]) -> tuple[list[PoseRecord], list[str]]:
    names = {i: n for n, i in frame_ids(scene).items()}
    recs = []
    for im_id, dets in zip(ids, model.frames, strict=True):
        for d in dets:
            T = Rigid3(d.R_cam_from_obj, d.t_cam_from_obj_m)
            recs.append(PoseRecord(im_id, names[im_id], None, -1, d.label, model.classes[d.label], d.score,
                                   d.box_xyxy, T, T, T, {}, d.mask))
    return recs, [names[i] for i in ids]


def test_heldout_eval_agrees_with_eval_pose(pose_bop: Path):
    ids = [0, 2, 4]
    model = _GtModel(pose_bop, ids)
    rep = evaluate(model, pose_bop, ids, pose_bop.parent.parent / "models", score_thresh=0.0)
    recs, names = _records(model, pose_bop, ids)
    ref = evaluate_run(recs, names, pose_bop, None)["detector"]
    assert rep["detection"] == ref["detection"]
    for name, c in ref["per_class"].items():
        assert rep["per_class"][name]["detection"] == c["detection"]
        assert rep["per_class"][name]["t_err_m"] == pytest.approx(c["t_err_m"], nan_ok=True)
        assert rep["per_class"][name]["r_err_deg"] == pytest.approx(c["r_err_deg"], nan_ok=True)
    # hand counts: the structure is not scored, GT parts under 10 % visible are don't-care, the corner box is the
    # only false positive of each frame whose class is scored
    ds = DetectionPoseDataset(pose_bop, ids)
    structure = ds.classes.names.index("structure")
    from cadalign.data.bop import BopScene

    scene = BopScene(pose_bop)
    care = [g for i in ids for g in gt_instances(scene, i, ds.classes.class_of_obj, masks=False)
            if g.label != structure and g.visib_fract >= 0.1]
    fp = sum(1 for dets in model.frames if dets[-1].label != structure)
    assert rep["summary"]["tp"] == len(care) > 0 and rep["summary"]["fn"] == 0 and rep["summary"]["fp"] == fp
    assert rep["summary"]["t_err_m_mean"] == pytest.approx(T_ERR_M, abs=1e-5)
    assert rep["summary"]["r_err_deg_median"] <= R_ERR_DEG + 1e-3
    assert rep["frames"] == 3 and rep["ids"] == ids and "matches" not in rep

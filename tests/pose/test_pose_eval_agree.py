"""``eval_heldout.json`` (train pose) and ``cadalign eval pose`` / ``infer --gt`` score the same poses alike."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.detect import frame_ids
from cadalign.infer.pipeline import PoseRecord
from cadalign.infer.run import evaluate_run
from cadalign.metrics.pose_eval import PoseEvalConfig, PosePrediction, counted, gt_instances
from cadalign.train.datasets import DetectionPoseDataset
from cadalign.train.pose_eval import STAGES, evaluate, stage_recall
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

    def stage_boxes(self, image) -> dict[str, torch.Tensor]:
        """Every stage holds the frame's GT boxes (asked after ``detect`` has answered all frames)."""
        dets = self.frames[self.calls % len(self.frames)]
        self.calls += 1
        boxes = torch.tensor(np.array([d.box_xyxy for d in dets]), dtype=torch.float32)
        probs = torch.nn.functional.one_hot(torch.tensor([d.label for d in dets]), len(self.classes)).float()
        return {"anchors": boxes, "proposals": boxes, "proposal_probs": probs}


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
    from cadalign.formats.bop import BopScene

    scene = BopScene(pose_bop)
    care = [g for i in ids for g in gt_instances(scene, i, ds.classes.class_of_obj, masks=False)
            if g.label != structure and g.visib_fract >= 0.1]
    fp = sum(1 for dets in model.frames if dets[-1].label != structure)
    assert rep["summary"]["tp"] == len(care) > 0 and rep["summary"]["fn"] == 0 and rep["summary"]["fp"] == fp
    assert rep["summary"]["t_err_m_mean"] == pytest.approx(T_ERR_M, abs=1e-5)
    assert rep["summary"]["r_err_deg_median"] <= R_ERR_DEG + 1e-3
    assert rep["frames"] == 3 and rep["ids"] == ids and "matches" not in rep
    # every stage of the stand-in holds the GT boxes: nothing is lost anywhere, and the counts are the scored ones
    assert set(rep["stage_recall"]) == {ds.classes.names[g.label] for g in care}
    assert sum(c["n"] for c in rep["stage_recall"].values()) == len(care)
    assert all(c[k] == 1.0 for c in rep["stage_recall"].values() for k in STAGES)


class _Stages:
    """A stand-in network whose stages lose chosen classes: proposals of ``no_proposal`` are moved half a box
    aside (IoU 1/3), the head gives ``weak_head`` probability 0.4, and anchors are the GT boxes."""

    def __init__(self, ds: DetectionPoseDataset, no_proposal: int, weak_head: int) -> None:
        self.classes, self.ds, self.i = ds.classes.names, ds, 0
        self.no_proposal, self.weak_head = no_proposal, weak_head

    def stage_boxes(self, image) -> dict[str, torch.Tensor]:
        item = self.ds[self.i]
        self.i += 1
        boxes, labels = item["boxes"].float(), item["labels"]
        moved = boxes.clone()
        shift = (boxes[:, 2] - boxes[:, 0]) / 2
        moved[labels == self.no_proposal, 0] += shift[labels == self.no_proposal]
        moved[labels == self.no_proposal, 2] += shift[labels == self.no_proposal]
        probs = torch.nn.functional.one_hot(labels, len(self.classes)).float()
        probs[labels == self.weak_head, self.weak_head] = 0.4
        probs[labels == self.weak_head, 0] = 0.6
        return {"anchors": boxes, "proposals": moved, "proposal_probs": probs}


def test_stage_recall_names_the_stage_that_loses_a_class(pose_bop: Path):
    ids = [0, 1, 2, 3, 4, 5]
    ds = DetectionPoseDataset(pose_bop, ids)
    names = ds.classes.names
    valve, hot_stab = names.index("valve"), names.index("hot_stab")
    model = _Stages(ds, no_proposal=hot_stab, weak_head=valve)
    # final detections: every valve and hot stab at its GT box, the valves scoring under the threshold
    preds = [PosePrediction(int(ds[i]["im_id"]), int(lab), 0.3 if lab == valve else 0.9, box.numpy().astype(float),
                            Rigid3(np.eye(3), np.zeros(3)))
             for i in range(len(ds)) for box, lab in zip(ds[i]["boxes"], ds[i]["labels"], strict=True)]
    rec = stage_recall(model, ds, preds, score_thresh=0.5)
    from cadalign.formats.bop import BopScene

    scene = BopScene(pose_bop)
    n = {c: sum(1 for i in ids for g in gt_instances(scene, i, ds.classes.class_of_obj) if g.label == c and counted(
        g, PoseEvalConfig())) for c in (valve, hot_stab)}
    assert n[valve] > 0 and n[hot_stab] > 0 and "structure" not in rec
    assert rec["valve"] == {"n": n[valve], "anchor": 1.0, "proposal": 1.0, "head": 0.0, "detection": 0.0}
    assert rec["hot_stab"] == {"n": n[hot_stab], "anchor": 1.0, "proposal": 0.0, "head": 0.0, "detection": 1.0}

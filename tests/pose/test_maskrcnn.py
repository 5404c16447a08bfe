"""The detector end to end on tiny inputs: losses, learning, inference interface, checkpoints, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from pose_testutils import TINY_K as K
from pose_testutils import tiny_cfg, tiny_pose_loss, tiny_scene
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.errors import TrainingError
from cadalign.models.maskrcnn import Detection, MaskRCNNPose, load_pose_model
from cadalign.models.maskrcnn.roi_heads import (
    SampledRoIs,
    context_windows,
    jitter_boxes,
    mask_targets,
    paste_masks,
    sample_rois,
)
from cadalign.models.ops import box_iou

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("param", "context"), [("improved", (1.0, 0.0)), ("thesis", (1.0, 0.0)),
                                              ("improved", (2.0, 16.0))])
def test_losses_decrease_on_a_tiny_image(param: str, context: tuple[float, float]):
    torch.manual_seed(0)
    cfg = tiny_cfg(pose=param, box_context=context[0], box_context_px=context[1])
    model = MaskRCNNPose(cfg, ["background", "square", "bar"])
    img, tgt = tiny_scene(0)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    totals = []
    for _ in range(25):
        losses = model(img[None], [tgt], pose_loss=tiny_pose_loss())
        total = sum(losses.values())
        opt.zero_grad()
        total.backward()
        opt.step()
        totals.append(float(total.detach()))
    expected = {"rpn_objectness", "rpn_box", "roi_cls", "roi_box", "mask"}
    expected |= {"pose_rot", "pose_trans"} if param == "improved" else {"pose_l1"}
    assert set(losses) == expected
    assert np.isfinite(totals).all()
    assert np.mean(totals[-5:]) < 0.6 * totals[0], totals


def test_context_windows_by_hand():
    rois = torch.tensor([[1.0, 10, 10, 14, 30], [0.0, 0, 0, 100, 60]])
    win, where = context_windows(rois, 2.0, 16.0)
    # box 1: 4 x 20 -> 16 (the floor) x 40 about (12, 20); box 2: 100 x 60 -> 200 x 120 about (50, 30)
    assert torch.allclose(win, torch.tensor([[1.0, 4, 0, 20, 40], [0.0, -50, -30, 150, 90]]))
    assert torch.allclose(where, torch.log(torch.tensor([[4 / 16, 20 / 40], [0.5, 0.5]])))
    same, zero = context_windows(rois, 1.0, 0.0)
    assert torch.equal(same, rois) and torch.equal(zero, torch.zeros(2, 2))


@pytest.mark.parametrize("context", [(1.0, 0.0), (3.0, 0.0), (1.0, 24.0)])
def test_box_head_sees_the_context_window_and_only_then(context: tuple[float, float]):
    torch.manual_seed(0)
    model = MaskRCNNPose(tiny_cfg(box_context=context[0], box_context_px=context[1]), ["background", "a"]).eval()
    assert model.box_head.fc1.in_features == 16 * 49 + (0 if context == (1.0, 0.0) else 2)
    # pyramid features: a 4 x 4 px RoI about (18, 18) on P2 (stride 4); a feature 8 px beside it, inside a 12 (3x)
    # or 24 px (floor) window, changes the head's output only when it pools that window (RoIAlign's bilinear
    # samples of the RoI itself reach x <= 19.9 px, i.e. cells 4 and 5)
    feats = [torch.zeros(1, 16, 12 >> i, 16 >> i) for i in range(4)]
    rois = torch.tensor([[0.0, 16, 16, 20, 20]])
    base = model._box_logits(feats, rois)
    feats[0][0, :, 4, 6] = 5.0  # the cell centred at x = 26, y = 18 px
    moved = model._box_logits(feats, rois)
    changed = not torch.allclose(base[0], moved[0])
    assert changed == (context != (1.0, 0.0))


def test_jittered_gt_copies_spread_as_asked_and_train_as_their_box():
    torch.manual_seed(0)
    gt = torch.tensor([[10.0, 10, 14, 22], [40, 0, 80, 20]])
    j = jitter_boxes(gt, 4000, 0.15)
    assert j.shape == (8000, 4) and jitter_boxes(gt, 0, 0.15).shape == (0, 4)
    for k, b in enumerate(gt):  # copies k, k + 2, ...: centre shift / side ~ N(0, 0.15), log size ~ N(0, 0.15)
        c = j[k::2]
        side = b[2:] - b[:2]
        shift = ((c[:, :2] + c[:, 2:]) / 2 - (b[:2] + b[2:]) / 2) / side
        logsize = torch.log((c[:, 2:] - c[:, :2]) / side)
        assert shift.mean(0).abs().max() < 0.01 and (shift.std(0) - 0.15).abs().max() < 0.01
        assert logsize.mean(0).abs().max() < 0.01 and (logsize.std(0) - 0.15).abs().max() < 0.01
    # a 4 x 12 part with no proposal near it: only its own box is a positive RoI, unless copies join
    proposals = [torch.tensor([[100.0, 100, 140, 140]])]
    target = {"boxes": gt[:1], "labels": torch.tensor([2])}
    plain = sample_rois(proposals, [target], 64, 0.5)
    moved = sample_rois(proposals, [target], 64, 0.5, jitter=8, jitter_sigma=0.15)
    assert int((plain.labels > 0).sum()) == 1
    pos = moved.labels > 0
    assert 2 <= int(pos.sum()) <= 9 and (moved.labels[pos] == 2).all() and (moved.gt_index[pos] == 0).all()
    iou = box_iou(gt[:1], moved.boxes)[0]
    assert (iou[pos] >= 0.5).all() and (iou[~pos] < 0.5).all()


def test_stage_boxes_are_the_networks_in_image_pixels():
    torch.manual_seed(1)
    model = MaskRCNNPose(tiny_cfg(), ["background", "square", "bar"]).eval()
    img, _ = tiny_scene(1)
    st = model.stage_boxes(img)
    feats = model._features(img[None])
    proposals, _ = model.rpn(feats, (48, 64))
    assert torch.equal(st["anchors"], model.rpn.anchors(feats)) and torch.equal(st["proposals"], proposals[0])
    assert st["proposal_probs"].shape == (len(proposals[0]), 3)
    assert torch.allclose(st["proposal_probs"].sum(1), torch.ones(len(proposals[0])))
    # an image twice the network's size: the same network boxes, in that image's pixels
    big = torch.nn.functional.interpolate(img[None], scale_factor=2, mode="bilinear", align_corners=False)[0]
    st2 = model.stage_boxes(big)
    assert torch.equal(st2["anchors"], 2 * st["anchors"])
    assert not model.training


def test_eval_outputs_and_detect_interface():
    torch.manual_seed(1)
    model = MaskRCNNPose(tiny_cfg(), ["background", "square", "bar"]).eval()
    img, _ = tiny_scene(1)
    out = model(img[None])
    assert isinstance(out, list) and len(out) == 1
    o = out[0]
    n = len(o["boxes"])
    assert o["masks"].shape == (n, 48, 64) and o["pose_raw"].shape == (n, 9) and o["mask_probs"].shape[1:] == (28, 28)
    # detect on an image twice the network size: boxes and masks come back in the input image's pixels
    big = torch.nn.functional.interpolate(img[None], scale_factor=2, mode="nearest")[0]
    dets = model.detect(big, torch.diag(torch.tensor([2.0, 2.0, 1.0])) @ K, score_thresh=0.0)
    assert dets and all(isinstance(d, Detection) for d in dets)
    assert set(model.last_timings) == {"detector", "mask", "pose"} and min(model.last_timings.values()) >= 0
    scores = [d.score for d in dets]
    assert scores == sorted(scores, reverse=True)
    for d in dets:
        assert d.mask.shape == (96, 128) and d.mask.dtype == bool
        assert d.box_xyxy.shape == (4,) and (d.box_xyxy >= -1e-4).all() and d.box_xyxy[2] <= 128 + 1e-4
        assert d.label in (1, 2)
        np.testing.assert_allclose(d.R_cam_from_obj @ d.R_cam_from_obj.T, np.eye(3), atol=1e-5)
        assert d.t_cam_from_obj_m.shape == (3,) and np.isfinite(d.t_cam_from_obj_m).all()
    assert model.detect(big, K, score_thresh=1.01) == []
    with pytest.raises(ValueError, match="image"):
        model.detect(img[None], K)


def test_mask_targets_and_paste_are_inverse():
    # a GT mask resampled into its own box and pasted back gives the same mask
    m = torch.zeros(1, 48, 64, dtype=torch.bool)
    m[0, 10:30, 5:45] = True
    m[0, 15:20, 20:25] = False
    box = torch.tensor([[5.0, 10, 45, 30]])
    rois = SampledRoIs(box, torch.zeros(1, dtype=torch.int64), torch.ones(1, dtype=torch.int64),
                       torch.zeros(1, dtype=torch.int64))
    tgt = mask_targets(rois, [{"masks": m}], 28)
    back = paste_masks(tgt, box, (48, 64))
    iou = (back & m).sum() / (back | m).sum()
    assert float(iou) > 0.95


def _train_tiny(scene: Path, out: Path, extra: list[str] | None = None):
    args = ["train", "pose", str(scene), "--out", str(out), "--preset", "fast",
            "--config", str(REPO / "training" / "pose_tiny.toml"), *(extra or [])]
    return CliRunner().invoke(app, args)


def test_cli_train_pose_end_to_end_resume_and_load(pose_bop: Path, tmp_path: Path):
    assert CliRunner().invoke(app, ["train", "pose", "--help"]).exit_code == 0
    out = tmp_path / "run"
    res = _train_tiny(pose_bop, out)
    assert res.exit_code == 0, res.output
    rows = json.loads((out / "metrics.json").read_text())["rows"]
    assert rows[-1]["step"] == 4 and {"mask", "pose_rot", "pose_trans"} <= set(rows[-1])
    report = json.loads((out / "eval_heldout.json").read_text())
    assert report["frames"] == len(report["ids"]) >= 1 and 0 <= report["summary"]["f1"] <= 1
    assert report["stage_recall"] and "structure" not in report["stage_recall"]
    for st in report["stage_recall"].values():
        assert st["n"] >= 1 and all(0 <= st[k] <= 1 for k in ("anchor", "proposal", "head", "detection"))
    # resume extends the run; the same folder with another parameterisation is refused
    res = _train_tiny(pose_bop, out, ["--resume", "--steps", "6"])
    assert res.exit_code == 0, res.output
    assert json.loads((out / "metrics.json").read_text())["rows"][-1]["step"] == 6
    res = _train_tiny(pose_bop, out, ["--pose", "thesis"])
    said = " ".join(res.output.split())  # the console wraps lines
    assert res.exit_code == 1 and "already holds a training run" in said and "--overwrite" in said
    res = _train_tiny(pose_bop, out, ["--pose", "thesis", "--resume"])
    assert res.exit_code == 1 and "different model_config" in " ".join(res.output.split())
    model, info = load_pose_model(out)
    assert info["step"] == 6 and info["classes"][0] == "background" and model.cfg.input_hw == (60, 80)
    item_img = torch.rand(3, 120, 160)
    K = torch.tensor([[120.0, 0, 80], [0, 120, 60], [0, 0, 1]])
    assert all(d.mask.shape == (120, 160) for d in model.detect(item_img, K, score_thresh=0.0))
    # --overwrite replaces the run: a fresh thesis run, its own record and metrics
    res = _train_tiny(pose_bop, out, ["--pose", "thesis", "--overwrite", "--steps", "2"])
    assert res.exit_code == 0, res.output
    record = json.loads((out / "train_config.json").read_text())
    assert record["task"] == "pose" and record["config"]["model"]["pose"] == "thesis"
    assert record["model_config"]["pose"] == "thesis" and record["classes"] == info["classes"]
    assert [r["step"] for r in json.loads((out / "metrics.json").read_text())["rows"]][-1] == 2
    assert load_pose_model(out)[1]["step"] == 2


def test_load_pose_model_refuses_foreign_or_missing(tmp_path: Path):
    with pytest.raises(TrainingError, match="no trained model"):
        load_pose_model(tmp_path / "nothing")
    (tmp_path / "seg" / "checkpoints").mkdir(parents=True)
    torch.save({"model": {}, "extra_state": {"task": "seg", "classes": ["background"]}},
               tmp_path / "seg" / "checkpoints" / "last.pt")
    with pytest.raises(TrainingError, match="not a detection\\+pose checkpoint"):
        load_pose_model(tmp_path / "seg")
    (tmp_path / "bad" / "checkpoints").mkdir(parents=True)
    (tmp_path / "bad" / "checkpoints" / "last.pt").write_bytes(b"garbage")
    with pytest.raises(TrainingError, match="not a readable checkpoint"):
        load_pose_model(tmp_path / "bad")

"""The detector end to end on tiny inputs: losses, learning, inference interface, checkpoints, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from pose_testutils import TINY_K as K
from pose_testutils import tiny_cfg, tiny_pose_loss, tiny_scene
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.errors import TrainingError
from cadalign.models.maskrcnn import Detection, MaskRCNNPose, load_pose_model
from cadalign.models.maskrcnn.roi_heads import (
    SampledRoIs,
    box_losses,
    context_windows,
    instance_weights,
    jitter_boxes,
    mask_targets,
    paste_masks,
    sample_balanced,
    sample_rois,
)
from cadalign.models.ops import box_iou

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("param", "context", "balance"), [("improved", (1.0, 0.0), False),
                                                         ("thesis", (1.0, 0.0), False),
                                                         ("improved", (2.0, 16.0), False),
                                                         ("improved", (1.0, 0.0), True)])
def test_losses_decrease_on_a_tiny_image(param: str, context: tuple[float, float], balance: bool):
    torch.manual_seed(0)
    cfg = tiny_cfg(pose=param, box_context=context[0], box_context_px=context[1], roi_balance=balance)
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


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(1, 30), min_size=1, max_size=8), st.integers(0, 40), st.integers(1, 64),
       st.integers(0, 2**31 - 1))
def test_balanced_positives_go_round_robin_over_instances(per_inst: list[int], n_neg: int, batch: int, seed: int):
    torch.manual_seed(seed)
    m = torch.cat([torch.full((n,), g) for g, n in enumerate(per_inst)] + [torch.full((n_neg,), -1)])
    m = m[torch.randperm(m.numel())]
    pos, neg = sample_balanced(m, m == -1, batch, 0.5)
    n_pos = min(batch // 2, sum(per_inst))
    assert pos.numel() == n_pos and neg.numel() == min(batch - n_pos, n_neg)
    assert (m[pos] >= 0).all() and (m[neg] == -1).all() and pos.unique().numel() == pos.numel()
    got = torch.bincount(m[pos], minlength=len(per_inst)).tolist()
    # round-robin: an instance with fewer draws than another's minus one has run out of candidates
    for a, ga in enumerate(got):
        assert ga <= per_inst[a]
        assert all(ga == per_inst[a] or ga >= gb - 1 for gb in got)


def test_instance_weights_give_each_instance_the_same_total_and_keep_the_loss_scale():
    gi = torch.tensor([0, 0, 0, 0, 1, 2, 2, -1, -1, -1])
    lab = torch.tensor([1, 1, 1, 1, 2, 3, 3, 0, 0, 0])
    w = instance_weights(gi, lab)
    # 7 positives over 3 instances: each instance weighs 7 / 3 in all; background 1
    for g in range(3):
        assert float(w[gi == g].sum()) == pytest.approx(7 / 3)
    assert torch.equal(w[lab == 0], torch.ones(3)) and float(w.sum()) == pytest.approx(10.0)
    torch.manual_seed(0)
    boxes = torch.rand(10, 2) * 50
    boxes = torch.cat([boxes, boxes + 5 + torch.rand(10, 2) * 20], 1)
    targets = [{"boxes": boxes[:3] + 1.0, "labels": torch.tensor([1, 2, 3])}]
    rois = SampledRoIs(boxes, torch.zeros(10, dtype=torch.long), lab, gi)
    logits, deltas = torch.randn(10, 4), torch.randn(10, 16)
    plain = box_losses(logits, deltas, rois, targets)
    ones = box_losses(logits, deltas, SampledRoIs(boxes, rois.image, lab, gi, torch.ones(10)), targets)
    weighted = box_losses(logits, deltas, SampledRoIs(boxes, rois.image, lab, gi, w), targets)
    for k in ("roi_cls", "roi_box"):
        assert float(ones[k]) == pytest.approx(float(plain[k]), rel=1e-6)
        assert float(weighted[k]) != pytest.approx(float(plain[k]), rel=1e-3)
    # a tiny part with one candidate beside a big one with many: uniform draws often miss it, balanced never
    big = torch.tensor([[0.0, 0, 100, 100]])
    props = [big + torch.randn(200, 4) for _ in range(1)]
    target = {"boxes": torch.tensor([[0.0, 0, 100, 100], [150, 150, 154, 154]]), "labels": torch.tensor([1, 2])}
    hits = [int((sample_rois(props, [target], 16, 0.25, balance=b).gt_index == 1).sum() > 0) for b in (False,) * 50]
    assert sum(hits) < 25
    for _ in range(20):
        r = sample_rois(props, [target], 16, 0.25, balance=True)
        assert int((r.gt_index == 1).sum()) == 1 and r.weight is not None
        assert float(r.weight[r.gt_index == 1].sum()) == pytest.approx(float(r.weight[r.gt_index == 0].sum()))


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
    for sr in report["stage_recall"].values():
        assert sr["n"] >= 1 and all(0 <= sr[k] <= 1 for k in ("anchor", "proposal", "head", "detection"))
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

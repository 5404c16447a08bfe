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
from cadalign.models.maskrcnn.roi_heads import SampledRoIs, mask_targets, paste_masks

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("param", ["improved", "thesis"])
def test_losses_decrease_on_a_tiny_image(param: str):
    torch.manual_seed(0)
    model = MaskRCNNPose(tiny_cfg(pose=param), ["background", "square", "bar"])
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

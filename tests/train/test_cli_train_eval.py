"""``cadalign train seg|depth`` and ``cadalign eval seg|depth``: help and a tiny end-to-end run."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.io import read_json

runner = CliRunner()


@pytest.mark.parametrize("cmd", [["train"], ["train", "seg"], ["train", "depth"], ["eval"], ["eval", "seg"],
                                 ["eval", "depth"]])
def test_help(cmd):
    res = runner.invoke(app, [*cmd, "--help"])
    assert res.exit_code == 0, res.output
    assert "Usage" in res.output


def test_seg_train_resume_eval(tiny_dense, tiny_seg_toml, tmp_path):
    run = tmp_path / "seg"
    res = runner.invoke(app, ["train", "seg", str(tiny_dense), "--out", str(run), "--config", str(tiny_seg_toml),
                              "--steps", "2", "--seed", "3"])
    assert res.exit_code == 0, res.output
    assert (run / "checkpoints" / "last.pt").is_file() and (run / "loss.png").is_file()
    again = runner.invoke(app, ["train", "seg", str(tiny_dense), "--out", str(run), "--config", str(tiny_seg_toml)])
    assert again.exit_code == 1 and "--resume" in again.output
    res = runner.invoke(app, ["train", "seg", str(tiny_dense), "--out", str(run), "--config", str(tiny_seg_toml),
                              "--steps", "3", "--seed", "3", "--resume"])
    assert res.exit_code == 0, res.output
    assert read_json(run / "metrics.json")["rows"][-1]["step"] == 3
    out = tmp_path / "eval_seg"
    res = runner.invoke(app, ["eval", "seg", str(tiny_dense), "--model", str(run), "--out", str(out),
                              "--figures", "1"])
    assert res.exit_code == 0, res.output
    m = read_json(out / "seg_metrics.json")
    assert set(m["iou"]) == {"background", "structure", "valve", "hot_stab"} and m["dataset"]["split"] == "test"
    assert 0 <= m["pixel_accuracy"] <= 1 and m["pixels"] == 160 * 120 and "scale 0.5" in m["protocol"]["resolution"]
    assert len(list(out.glob("seg_*.png"))) == 1 and m["protocol"]["test_time_augmentation"] == "none"
    res = runner.invoke(app, ["eval", "seg", str(tiny_dense), "--model", str(run), "--out", str(tmp_path / "tta"),
                              "--figures", "0", "--flip-tta"])
    assert res.exit_code == 0, res.output
    tta = read_json(tmp_path / "tta" / "seg_metrics.json")
    assert tta["protocol"]["test_time_augmentation"] == "mean of the frame and its mirror"


def test_depth_train_eval_and_wrong_task(tiny_dense, tiny_depth_toml, tmp_path):
    run = tmp_path / "depth"
    res = runner.invoke(app, ["train", "depth", str(tiny_dense), "--out", str(run), "--config", str(tiny_depth_toml)])
    assert res.exit_code == 0, res.output
    out = tmp_path / "eval_depth"
    res = runner.invoke(app, ["eval", "depth", str(tiny_dense), "--model", str(run), "--out", str(out),
                              "--split", "val", "--max-depth", "50"])
    assert res.exit_code == 0, res.output
    m = read_json(out / "depth_metrics.json")
    assert m["protocol"]["cap_m"] == [0.001, 50.0] and m["protocol"]["alignment"] == "none"
    assert {"all", "structure", "valve", "hot_stab"} <= set(m["metrics"])
    assert m["metrics"]["all"]["frames"] == 1 and 0 <= m["metrics"]["all"]["delta1"] <= 1
    assert list(out.glob("depth_*.png"))
    res = runner.invoke(app, ["eval", "seg", str(tiny_dense), "--model", str(run), "--out", str(out)])
    assert res.exit_code == 1 and "not 'seg'" in res.output
    res = runner.invoke(app, ["train", "depth", str(tiny_dense), "--out", str(tmp_path / "x"), "--preset", "huge"])
    assert res.exit_code == 1 and "allowed presets" in res.output

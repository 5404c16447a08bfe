"""End to end on a tiny simulated dive: CLI run with --gt, resume, config refusal, failure modes."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.config import resolve
from cadalign.errors import ConfigError, InputError
from cadalign.io import write_image
from cadalign.sfm import PRESETS, SfMConfig, run
from cadalign.sfm.pipeline import STEPS

REPO = Path(__file__).resolve().parents[2]
runner = CliRunner()


@pytest.fixture(scope="module")
def sfm_out(tiny_dive: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``cadalign sfm FRAMES --out OUT --gt SIM`` through the CLI (balanced preset)."""
    out = tmp_path_factory.mktemp("sfm") / "out"
    res = runner.invoke(app, ["sfm", str(tiny_dive / "frames"), "--out", str(out), "--gt", str(tiny_dive),
                              "--set", "num_threads=1"])  # one thread: deterministic
    assert res.exit_code == 0, res.output
    return out


def test_sfm_help():
    res = runner.invoke(app, ["sfm", "--help"])
    assert res.exit_code == 0
    for opt in ("--out", "--preset", "--gt", "--overwrite", "--config", "--set", "--calib"):
        assert opt in res.output


def test_tiny_dive_registers_accurately(sfm_out: Path):
    report = json.loads((sfm_out / "sfm_report.json").read_text())
    gt = report["gt"]
    assert report["frames_in"] == 10
    assert gt["registration_rate"] >= 0.9
    # 10 frames span a 28 deg arc: the centre-based Sim(3) cannot pin the roll about the arc, so the
    # absolute rotation error is loose; the gauge-free relative error is the sharp check
    assert gt["rel_rot_err_deg_mean"] < 0.3 and gt["rot_err_deg_max"] < 5.0
    assert gt["centre_rmse_rel"] < 0.01
    assert report["points"] > 200 and report["mean_reprojection_error_px"] < 1.0
    assert 0 < gt["sfm_depth"]["coverage_mean"] < 0.05 and gt["sfm_depth"]["abs_rel_median"] < 0.05
    assert set(report["seconds"]) == set(STEPS)


def test_outputs_have_the_documented_layout(sfm_out: Path, tiny_dive: Path):
    for rel in ("sparse/0/cameras.bin", "sparse/0/images.bin", "sparse/0/points3D.bin", "database.db",
                "frames.json", "trajectory.png", "trajectory_vs_gt.png", "cadalign_stage.json"):
        assert (sfm_out / rel).is_file(), rel
    cams = json.loads((sfm_out / "cameras.json").read_text())
    gt_cams = json.loads((tiny_dive / "gt" / "sim" / "000000" / "cameras.json").read_text())
    assert cams["units"] == "sfm"
    name = sorted(cams["frames"])[0]
    assert set(cams["frames"][name]) == set(gt_cams["frames"][name])  # the simulator's format
    assert set(cams["frames"]) <= set(gt_cams["frames"])
    depth = np.load(sfm_out / "depth" / f"{Path(name).stem}.npy")
    assert depth.dtype == np.float32 and depth.shape == (240, 320)
    assert depth.min() == 0 and depth.max() > 0


def test_rerun_reuses_every_step(sfm_out: Path, tiny_dive: Path):
    markers = {s: (sfm_out / "steps" / f"{s}.json").stat().st_mtime_ns for s in STEPS}
    before = json.loads((sfm_out / "sfm_report.json").read_text())
    cfg = resolve(SfMConfig, PRESETS, "balanced", overrides={"num_threads": 1})  # what the CLI resolved
    run(cfg, tiny_dive / "frames", sfm_out)
    assert {s: (sfm_out / "steps" / f"{s}.json").stat().st_mtime_ns for s in STEPS} == markers
    after = json.loads((sfm_out / "sfm_report.json").read_text())
    assert after["seconds"] == before["seconds"] and "gt" in after


def test_interrupted_run_resumes_from_the_missing_step(sfm_out: Path, tiny_dive: Path, tmp_path: Path):
    import shutil

    out = tmp_path / "copy"
    shutil.copytree(sfm_out, out)
    (out / "steps" / "mapping.json").unlink()  # as if killed during mapping
    kept = {s: (out / "steps" / f"{s}.json").stat().st_mtime_ns for s in ("frames", "features", "matches")}
    run(resolve(SfMConfig, PRESETS, "balanced", overrides={"num_threads": 1}), tiny_dive / "frames", out)
    assert {s: (out / "steps" / f"{s}.json").stat().st_mtime_ns for s in kept} == kept
    assert (out / "steps" / "mapping.json").is_file() and (out / "steps" / "export.json").is_file()
    assert "gt" not in json.loads((out / "sfm_report.json").read_text())  # the model changed: stale gt dropped


def test_other_config_is_refused_unless_overwrite(sfm_out: Path, tiny_dive: Path):
    cfg = PRESETS["fast"]
    with pytest.raises(ConfigError, match="--overwrite"):
        run(cfg, tiny_dive / "frames", sfm_out)


def test_blank_frames_raise_too_few_features_naming_them(tmp_path: Path):
    rng = np.random.default_rng(0)
    frames = tmp_path / "frames"
    for k in range(4):
        img = np.full((120, 160, 3), 90, np.uint8)  # murky nothing
        if k == 0:
            img = rng.integers(0, 255, (120, 160, 3), dtype=np.uint8)  # one noisy frame has features
        write_image(frames / f"{k:06d}.png", img)
    cfg = dataclasses.replace(PRESETS["fast"], frames=dataclasses.replace(PRESETS["fast"].frames, min_motion=0.0,
                                                                          blur_ratio=0.0, enhance="none"))
    with pytest.raises(InputError, match="too few features") as exc:
        run(cfg, frames, tmp_path / "out")
    assert "000001.png (0)" in str(exc.value) and "000003.png" in str(exc.value)
    res = runner.invoke(app, ["sfm", str(frames), "--out", str(tmp_path / "out2"), "--preset", "fast",
                              "--set", "frames.min_motion=0", "--set", "frames.blur_ratio=0"])
    assert res.exit_code == 1 and "too few features" in " ".join(res.output.split())


def test_bad_inputs_and_keys_fail_readably(tmp_path: Path):
    res = runner.invoke(app, ["sfm", str(tmp_path / "missing"), "--out", str(tmp_path / "o")])
    assert res.exit_code == 1 and "not found" in res.output
    (tmp_path / "f").mkdir()
    res = runner.invoke(app, ["sfm", str(tmp_path / "f"), "--out", str(tmp_path / "o"), "--set", "matching.overlp=3"])
    assert res.exit_code == 1 and "did you mean 'matching.overlap'" in " ".join(res.output.split())
    res = runner.invoke(app, ["sfm", str(tmp_path / "f"), "--out", str(tmp_path / "o"), "--preset", "best"])
    assert res.exit_code == 1 and "allowed presets" in " ".join(res.output.split())


def test_too_few_frames_left_after_selection_says_so(tmp_path: Path):
    frames = tmp_path / "frames"
    rng = np.random.default_rng(1)
    a, b = (rng.integers(0, 255, (120, 160, 3), dtype=np.uint8) for _ in range(2))
    for k, img in enumerate((a, b, b, b)):  # two distinct frames, then near-duplicates of the second
        write_image(frames / f"{k:06d}.png", img)
    with pytest.raises(InputError, match=r"only 2 frame\(s\) left for SfM after frame selection"):
        run(PRESETS["fast"], frames, tmp_path / "out")

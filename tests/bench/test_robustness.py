"""Low-visibility sweep: scene variants, the GT contrast metric on hand images, and a tiny end-to-end run."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from cadalign.bench.data import bench_scene, write_scene_variant
from cadalign.bench.report import write_bench_report
from cadalign.errors import ConfigError
from cadalign.evaluate.robustness import SEVERITIES, condition_scene, conditions, contrast_metrics, run_robustness
from cadalign.sim.spec import default_scene_path, load_scene


def test_condition_scenes_change_one_factor(tmp_path):
    base_path = bench_scene(tmp_path)
    base = load_scene(base_path)
    assert base == load_scene(default_scene_path()) and base.trajectory.fps == 1.0

    def variant(effect, value):
        return load_scene(write_scene_variant(tmp_path / f"{effect}.yaml", base_path,
                                              condition_scene(base_path, effect, value)))

    turbid = variant("turbidity", "7C")
    assert turbid.water.jerlov == "7C" and base.water.jerlov == "IB"
    assert turbid == replace(base, water=replace(base.water, jerlov="7C"))
    snow = variant("marine_snow", 400.0)
    assert snow.effect_params["marine_snow"]["density_per_m3"] == 400.0
    assert base.effect_params.get("marine_snow", {}).get("density_per_m3") != 400.0
    assert replace(snow, effect_params=base.effect_params) == base
    dark = variant("light", 0.1)
    assert dark.ambient == pytest.approx(0.035)
    assert [lt.intensity for lt in dark.lights] == pytest.approx([16.0, 16.0])
    assert [replace(lt, intensity=b.intensity) for lt, b in zip(dark.lights, base.lights, strict=True)] == list(
        base.lights)
    with pytest.raises(ConfigError, match="allowed"):
        condition_scene(base_path, "fog", 1)
    murky = write_scene_variant(tmp_path / "murky.yaml", base_path, {"water": {"jerlov": "3C"}})
    with pytest.raises(ConfigError, match="baseline is Jerlov IB"):
        condition_scene(murky, "turbidity", "7C")
    with pytest.raises(ValueError, match=".yaml"):
        write_scene_variant(tmp_path / "x.toml", base_path, {})


def test_conditions_have_three_severities_of_three_effects():
    conds = conditions("small")
    assert conds[0][0] == "baseline"
    for effect in SEVERITIES:
        assert len([c for c in conds if c[0] == effect]) == 3
    assert len([c for c in conditions("full") if c[0] == "light"]) == 4


def test_contrast_hand_cases():
    cls = np.zeros((4, 4), np.uint8)
    cls[:2] = 2  # top half structure
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[:2] = 204  # L = 0.8
    rgb[2:] = 51  # L = 0.2
    m = contrast_metrics(rgb, cls)
    assert m["contrast"] == pytest.approx(0.6) and m["rms_contrast_fg"] == pytest.approx(0.0)
    rgb[0] = 102  # structure rows at 0.4 and 0.8: std 0.2, mean 0.6
    assert contrast_metrics(rgb, cls)["rms_contrast_fg"] == pytest.approx(0.2 / 0.6, abs=1e-3)
    assert contrast_metrics(np.zeros((4, 4, 3), np.uint8), cls)["contrast"] == 0.0
    assert contrast_metrics(rgb, np.zeros((4, 4), np.uint8))["contrast"] == 0.0
    with pytest.raises(ValueError, match="differ"):
        contrast_metrics(rgb, np.zeros((3, 4), np.uint8))


def test_tiny_robustness_run_without_sfm(tmp_path, shared_data, monkeypatch):
    """Baseline + the third severity of turbidity and light (the full list is the slow test below)."""
    from cadalign.evaluate import robustness

    conds = [("baseline", "0", None), ("turbidity", "3", SEVERITIES["turbidity"][2]),
             ("light", "3", SEVERITIES["light"][2])]
    monkeypatch.setattr(robustness, "conditions", lambda size: conds)
    out = tmp_path / "rob"
    res = run_robustness(out, size="tiny", with_sfm=False, resolution=(48, 36), frames=1)
    assert len(res["rows"]) == 3 and set(res["plots"]) == {"turbidity", "light"}
    for name in res["plots"].values():
        assert (out / name).read_bytes()[:4] == b"\x89PNG"
    by = {(r["effect"], r["severity"]): r["metrics"]["contrast"] for r in res["rows"]}
    # murkier water washes the structure into the background
    assert by[("turbidity", "3")] < by[("baseline", "0")]
    rms = {(r["effect"], r["severity"]): r["metrics"]["rms_contrast_fg"] for r in res["rows"]}
    assert rms[("light", "3")] != rms[("baseline", "0")]
    again = run_robustness(out, size="tiny", with_sfm=False, resolution=(48, 36), frames=1)
    assert again["rows"] == res["rows"]
    html = write_bench_report(out).read_text()
    assert "<h2 id='robustness'>" in html and "alt='robustness light'" in html
    # with a (2-step) segmentation network: its mIoU under each condition
    from cadalign.models.resunet import ResUNetConfig
    from cadalign.train.loop import LoopConfig
    from cadalign.train.seg import SegTrainConfig, train_seg

    base_scene = next(out.glob("data/robustness_*/baseline_0")) / "gt" / "sim" / "000000"
    train_seg(SegTrainConfig(model=ResUNetConfig(base_channels=4, depth=3), scale=1.0,
                             loop=LoopConfig(steps=2, batch_size=1, checkpoint_every=2, log_every=1)),
              base_scene, tmp_path / "models" / "seg", split="all", val_split=None)
    with_models = run_robustness(out, size="tiny", with_sfm=False, resolution=(48, 36), frames=1,
                                 models=tmp_path / "models")
    assert all(0.0 <= r["metrics"]["miou"] <= 1.0 for r in with_models["rows"])


@pytest.mark.slow
def test_small_robustness_with_sfm(tmp_path, shared_data):
    res = run_robustness(tmp_path, size="tiny")
    assert len(res["rows"]) == 10
    base = res["rows"][0]["metrics"]
    assert base["registration_rate"] >= 0.75
    worst_light = [r for r in res["rows"] if r["effect"] == "light"][-1]["metrics"]
    assert worst_light["contrast"] < base["contrast"]


def test_plot_robustness_three_effects_three_severities(tmp_path):
    from cadalign.evaluate.robustness import plot_robustness

    rows = [{"effect": "baseline", "severity": "0", "value": None,
             "metrics": {"contrast": 0.5, "registration_rate": 1}}]
    for e, vals in SEVERITIES.items():
        rows += [{"effect": e, "severity": str(i + 1), "value": v,
                  "metrics": {"contrast": 0.4 - 0.1 * i, "registration_rate": None}} for i, v in enumerate(vals[:3])]
    files = plot_robustness({"rows": rows}, tmp_path)
    assert sorted(files) == sorted(SEVERITIES)
    assert all((tmp_path / f).stat().st_size > 1000 for f in files.values())

"""``cadalign bench infer``: the whole infer pipeline per preset, costs over the detector alone of the same run."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from cadalign.bench.registry import current_records, load_bench
from cadalign.cli.main import app

runner = CliRunner()


def _records(out: Path) -> dict[str, dict]:
    st = load_bench(out)["stages"]["infer"]
    return {r["name"]: r for r in current_records(st, st["current"])}


def test_tiny_infer_sweep_then_a_given_model(tmp_path: Path):
    out = tmp_path / "bench"
    res = runner.invoke(app, ["bench", "infer", "--size", "tiny", "--repeats", "1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    recs = _records(out)
    assert list(recs) == ["detector only", "fast", "balanced"]
    assert all(r["status"] == "done" for r in recs.values()), [r.get("error") for r in recs.values()]
    base = recs["detector only"]
    assert base["cost_ratio"] == 1.0 and base["metrics"]["ms_refinement"] == 0.0
    for r in recs.values():
        m = r["metrics"]
        assert m["frames"] == 6 and m["ms_detector"] > 0 and m["frames_per_s"] > 0
        assert r["cost_ratio"] == r["cost"] / base["cost"] and r["cost"] == m["ms_per_frame"]
        assert 0 <= m["add_s_01d"] <= 1
    assert "x1.00 the detector alone" in res.output.replace("\n", " ")
    assert "<h2 id='infer'>" in (out / "bench.html").read_text()
    # the short-trained network, given back as --model on two of the clip's frames: new records, same folder
    clip = next((out / "data").glob("clip_160x120_6_s0"))
    net = next((out / "data" / "work" / "infer").glob("pose_*"))
    args = ["bench", "infer", "--size", "tiny", "--repeats", "1", "--out", str(out), "--model", str(net),
            "--frames", str(clip / "frames"), "--gt", str(clip), "--cad", str(out / "data" / "scene.yaml"),
            "--max-frames", "2"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    given = _records(out)
    assert all(r["metrics"]["frames"] == 2 and "source" in r["knobs"] for r in given.values())
    assert len(json.loads((out / "bench.json").read_text())["stages"]["infer"]["points"]) == 6  # both kept


def test_model_options_are_checked_before_anything_runs(tmp_path: Path):
    res = runner.invoke(app, ["bench", "infer", "--frames", str(tmp_path), "--out", str(tmp_path / "b")])
    assert res.exit_code == 1 and "go with --model" in res.output
    res = runner.invoke(app, ["bench", "infer", "--model", str(tmp_path), "--frames", str(tmp_path),
                              "--out", str(tmp_path / "b")])
    assert res.exit_code == 1 and "--gt, --cad" in res.output
    bad = tmp_path / "bad.toml"
    bad.write_text("no_such_key = 1\n")
    res = runner.invoke(app, ["bench", "infer", "--model", str(tmp_path), "--frames", str(tmp_path), "--gt",
                              str(tmp_path), "--cad", str(tmp_path), "--config", str(bad),
                              "--out", str(tmp_path / "b")])
    assert res.exit_code == 1 and "no_such_key" in res.output
    assert not (tmp_path / "b" / "bench.json").exists()


def test_settings_with_the_same_override_keys_get_their_own_folders():
    from cadalign.bench.sweeps.infer import run_folder_name

    a = run_folder_name("balanced", {"refine": {"yaw_hypotheses": 4}})
    b = run_folder_name("balanced", {"refine": {"yaw_hypotheses": 8}})
    assert a != b and a.startswith("balanced_") and a == run_folder_name("balanced", {"refine": {"yaw_hypotheses": 4}})
    assert run_folder_name("fast", {}) == "fast"

"""``cadalign bench``: --help of every subcommand, tiny end-to-end runs of cheap stages, resume, the HTML."""

from __future__ import annotations

import base64
import json

import pytest
from bench_testdata import CHEAP_STAGES
from typer.testing import CliRunner

from cadalign.bench.registry import STAGES, load_bench
from cadalign.bench.report import recommendations
from cadalign.cli.main import app

runner = CliRunner()


@pytest.mark.parametrize("cmd", ["all", "robustness", *STAGES])
def test_help(cmd):
    res = runner.invoke(app, ["bench", cmd, "--help"])
    assert res.exit_code == 0, res.output
    assert "--out" in res.output
    if cmd != "robustness":
        assert "--size" in res.output


def test_bench_sim_help_keeps_per_effect_mode():
    res = runner.invoke(app, ["bench", "sim", "--help"])
    assert "--frames" in res.output and "--resolution" in res.output and "--sweep" in res.output


def test_unknown_size_is_a_one_line_error(tmp_path):
    res = runner.invoke(app, ["bench", "render", "--size", "huge", "--out", str(tmp_path)])
    assert res.exit_code == 1
    assert "unknown bench size 'huge'" in res.output and "tiny" in res.output


def test_all_rejects_unknown_skip(tmp_path):
    res = runner.invoke(app, ["bench", "all", "--skip", "nope", "--out", str(tmp_path)])
    assert res.exit_code != 0


def test_tiny_cheap_stages_end_to_end(tiny_bench):
    bench = load_bench(tiny_bench)
    assert bench["config"] == {"size": "tiny", "repeats": 1, "seed": 0}
    for stage in CHEAP_STAGES:
        st = bench["stages"][stage]
        recs = [st["points"][k] for k in st["current"]]
        assert len(recs) >= 3 and all(r["status"] == "done" for r in recs), [r.get("error") for r in recs]
        assert st["recommended"] in [r["name"] for r in recs]
        assert (tiny_bench / f"pareto_{stage}.png").read_bytes()[:4] == b"\x89PNG"
    render = {r["name"]: r for r in bench["stages"]["render"]["points"].values()}
    # finer renders agree better with the 2x reference
    assert render["40x30"]["accuracy"] < render["80x60"]["accuracy"] < render["160x120"]["accuracy"] <= 1.0
    align = {r["name"]: r for r in bench["stages"]["align"]["points"].values()}
    assert align["30 it x5+refine"]["metrics"]["pose_rms_mm"] < 5.0  # recovers the known Sim(3) to mm
    assert align["1 it"]["metrics"]["pose_rms_mm"] > align["10 it"]["metrics"]["pose_rms_mm"]
    emulate = {r["name"]: r for r in bench["stages"]["emulate"]["points"].values()}
    # both engines are exact: the same rays sample the surface identically
    assert emulate["bvh 8x360"]["accuracy"] == pytest.approx(emulate["torch 8x360"]["accuracy"], rel=1e-5)
    assert emulate["bvh 8x360"]["accuracy"] > emulate["bvh 32x1440"]["accuracy"]  # more rays, smaller gaps
    # Open3D alone on the densest BVH setting's rays is the baseline: same rays, same surface sampling
    base = emulate["32x1440 Open3D raycast alone"]
    assert bench["stages"]["emulate"]["baseline"] == base["name"] and base["cost_ratio"] == pytest.approx(1.0)
    assert base["metrics"]["open3d_gap_m"] == pytest.approx(emulate["bvh 32x1440"]["accuracy"], rel=1e-3)
    assert all(r["metrics"]["cost_vs_open3d"] > 0 and r["cost_ratio"] > 0 for r in emulate.values())
    assert base["name"] not in bench["stages"]["emulate"]["pareto"]
    fuse = {r["name"]: r for r in bench["stages"]["fuse"]["points"].values()}
    assert fuse["16 cm"]["metrics"]["chamfer_m"] > fuse["4 cm"]["metrics"]["chamfer_m"]
    assert fuse["4 cm"]["metrics"]["label_accuracy"] > 0.8 and fuse["4 cm"]["metrics"]["frames_per_s"] > 0


def test_html_lists_recommendations_with_inlined_plots(tiny_bench):
    html = (tiny_bench / "bench.html").read_text()
    assert "src='data:image/png;base64," in html and "<img alt='Pareto plot render'" in html
    for r in recommendations(load_bench(tiny_bench)):
        assert f"<h2 id='{r['stage']}'>" in html
        assert f"<span class='rec'>{r['recommended setting']}</span>" in html
    blob = html.split("src='data:image/png;base64,")[1].split("'")[0]
    assert base64.b64decode(blob)[:4] == b"\x89PNG"


def test_html_shows_each_baseline_ratio_beside_the_pareto_plot(tiny_bench):
    html = (tiny_bench / "bench.html").read_text()
    bench = load_bench(tiny_bench)
    for stage in ("emulate", "fuse"):
        section = html.split(f"<h2 id='{stage}'>")[1].split("<h2 id=")[0]
        row = section.split("<div class='plotrow'>")[1]
        assert row.startswith(f"<img alt='Pareto plot {stage}'") and "<div class='baseline'>" in row
        assert f"cost / {bench['stages'][stage]['baseline']}" in row
    assert "Open3D alone on its rays" in html and "Open3D VBG alone frames/s" in html
    assert "<div class='baseline'>" not in html.split("<h2 id='render'>")[1].split("<h2 id=")[0]  # no baseline


def test_rerun_reuses_finished_settings(tiny_bench):
    before = json.loads((tiny_bench / "bench.json").read_text())["stages"]["render"]["points"]
    res = runner.invoke(app, ["bench", "render", "--size", "tiny", "--repeats", "1", "--out", str(tiny_bench)])
    assert res.exit_code == 0, res.output
    after = json.loads((tiny_bench / "bench.json").read_text())["stages"]["render"]["points"]
    assert after == before  # same records: nothing was re-measured


def test_other_config_in_same_folder_is_refused(tiny_bench):
    res = runner.invoke(app, ["bench", "render", "--size", "tiny", "--repeats", "2", "--out", str(tiny_bench)])
    assert res.exit_code == 1 and "--overwrite" in res.output


def test_bench_sfm_runs_plain_pycolmap_as_its_baseline(tmp_path, shared_data):
    res = runner.invoke(app, ["bench", "sfm", "--size", "tiny", "--repeats", "1", "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    st = load_bench(tmp_path)["stages"]["sfm"]
    recs = {st["points"][k]["name"]: st["points"][k] for k in st["current"]}
    assert st["baseline"] == "plain pycolmap" and list(recs)[0] == "plain pycolmap"
    assert all(r["status"] == "done" for r in recs.values()), [r.get("error") for r in recs.values()]
    assert recs["plain pycolmap"]["cost_ratio"] == pytest.approx(1.0)
    assert all(r["cost_ratio"] > 0 and r["metrics"]["registration_rate"] > 0.5 for r in recs.values())
    html = (tmp_path / "bench.html").read_text()
    assert "cost / plain pycolmap" in html.split("<div class='plotrow'>")[1]

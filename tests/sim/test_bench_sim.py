"""``cadalign bench sim`` end to end on the tiny scene."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.io import read_image, read_json


def test_bench_sim_cli_writes_json_and_plot(tmp_path: Path, tiny_scene_file: Path) -> None:
    res = CliRunner().invoke(app, ["bench", "sim", str(tiny_scene_file), "--out", str(tmp_path), "--frames", "2"])
    assert res.exit_code == 0, res.output
    r = read_json(tmp_path / "bench_sim.json")
    med = r["seconds_per_frame_median"]
    assert set(r["effects"]) == {k.split(":", 1)[1] for k in med if k.startswith("effect:")}
    assert len(r["effects"]) == 8 and all(med[k] > 0 for k in med)
    assert len(r["samples"]["bare"]) == 3 * len(r["frames"])  # three alternating rounds per frame
    assert abs(r["effect_free_overhead_pct"]) < 100
    assert r["ratio_to_bare"]["all_effects"] > 0
    assert read_image(tmp_path / "bench_sim.png").shape[0] > 100

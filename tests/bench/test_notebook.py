"""notebooks/02_bench.ipynb runs in a Jupyter kernel against a tiny bench output (and a demo summary)."""

from __future__ import annotations

from notebook_testdata import execute_notebook

from cadalign.io import write_json


def test_bench_notebook_executes(tiny_bench, tmp_path):
    demo = tmp_path / "demo"
    write_json(demo / "summary.json", {"stages": {"sim": {"status": "done", "seconds": 3.0}}})
    nb = execute_notebook("02_bench.ipynb", {"CADALIGN_BENCH_DIR": str(tiny_bench), "CADALIGN_DEMO_DIR": str(demo)})
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert 3 <= len(code) <= 8
    text = "".join(o.get("text", "") for c in code for o in c.outputs)
    assert "'size': 'tiny'" in text
    bench_stages = [p.name for p in (tiny_bench / "notebook_plots").glob("pareto_*.png")]
    assert bench_stages
    images = sum("image/png" in o.get("data", {}) for c in code for o in c.outputs)
    assert images >= len(bench_stages) + 1  # a Pareto plot per stage and the demo's time per stage

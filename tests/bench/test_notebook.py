"""notebooks/02_bench.ipynb runs against a tiny bench output (code cells executed in-process: nbclient is
not installed)."""

from __future__ import annotations

import json

import matplotlib

from cadalign.io import write_json

matplotlib.use("Agg")


def test_bench_notebook_executes(tiny_bench, repo_root, tmp_path, monkeypatch):
    nb = json.loads((repo_root / "notebooks" / "02_bench.ipynb").read_text())
    cells = ["".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code"]
    assert 3 <= len(cells) <= 8
    for src in cells:  # only cadalign (and matplotlib for display) is imported
        for line in src.splitlines():
            if line.startswith(("import ", "from ")):
                assert line.split()[1].split(".")[0] in {"os", "pathlib", "matplotlib", "cadalign"}, line
    demo = tmp_path / "demo"
    write_json(demo / "summary.json", {"stages": {"sim": {"status": "done", "seconds": 3.0}}})
    monkeypatch.setenv("CADALIGN_BENCH_DIR", str(tiny_bench))
    monkeypatch.setenv("CADALIGN_DEMO_DIR", str(demo))
    ns: dict = {}
    for src in cells:
        exec(compile(src, "02_bench.ipynb", "exec"), ns)  # noqa: S102
    assert ns["bench"]["config"]["size"] == "tiny"
    for stage in ns["bench"]["stages"]:
        assert (tiny_bench / "notebook_plots" / f"pareto_{stage}.png").is_file()
    assert ns["stages"] == {"sim": 3.0}

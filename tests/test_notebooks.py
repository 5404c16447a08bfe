"""The notebooks run top to bottom in a real Jupyter kernel (nbclient + ipykernel, the dev extra) on tiny
settings: ``CADALIGN_NOTEBOOK_TINY=1`` switches their parameter cell to a small capture and a few steps, and
``CADALIGN_NOTEBOOK_OUT`` sends their outputs to a temporary folder. 02_bench runs in tests/bench (it needs
that folder's tiny bench fixture) through :func:`execute_notebook`."""

from __future__ import annotations

from pathlib import Path

import pytest
from notebook_testdata import execute_notebook

REPO = Path(__file__).resolve().parents[1]


def _images(nb: object) -> int:
    return sum("image/png" in out.get("data", {}) for c in nb.cells if c.cell_type == "code" for out in c.outputs)


def test_pipeline_notebook_runs_video_to_map(tmp_path: Path, shared_data: Path) -> None:
    """00_pipeline: simulate -> build-dataset (or its gate's refusal) -> 2 training steps -> infer -> fuse."""
    nb = execute_notebook("00_pipeline.ipynb", {"CADALIGN_NOTEBOOK_TINY": "1", "CADALIGN_NOTEBOOK_OUT": str(tmp_path),
                                                "CADALIGN_DATA_DIR": str(shared_data)})
    assert (tmp_path / "infer" / "poses.jsonl").is_file() and (tmp_path / "fuse" / "fuse_report.json").is_file()
    assert (tmp_path / "train" / "pose" / "checkpoints" / "last.pt").is_file()
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "learning from" in text and "2 steps" in text and "chamfer" in text
    assert _images(nb) >= 5


def test_simulate_notebook_runs(tmp_path: Path, shared_data: Path) -> None:
    nb = execute_notebook("01_simulate.ipynb", {"CADALIGN_NOTEBOOK_TINY": "1", "CADALIGN_NOTEBOOK_OUT": str(tmp_path),
                                                "CADALIGN_DATA_DIR": str(shared_data)})
    assert (tmp_path / "notebook_sim" / "contact_sheet.png").is_file()
    assert _images(nb) >= 2


def test_track_notebook_tracks_a_capture_from_a_rough_fix(tmp_path: Path, shared_data: Path) -> None:
    """03_track: simulate 6 small frames, track them RGB only from the first frame's rough fix, plot, score."""
    nb = execute_notebook("03_track.ipynb", {"CADALIGN_NOTEBOOK_TINY": "1", "CADALIGN_NOTEBOOK_OUT": str(tmp_path),
                                             "CADALIGN_DATA_DIR": str(shared_data)})
    assert (tmp_path / "track" / "poses.jsonl").is_file() and (tmp_path / "track" / "truth_errors.png").is_file()
    text = "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.outputs)
    assert "6 of 6 frames tracked" in text and "valve" in text
    assert _images(nb) >= 3


@pytest.mark.parametrize("name", sorted(p.name for p in (REPO / "notebooks").glob("*.ipynb")))
def test_every_notebook_is_run_by_a_test(name: str) -> None:
    """A new notebook needs its own run above (or in tests/bench for the bench one)."""
    here = Path(__file__).read_text()
    bench = (REPO / "tests" / "bench" / "test_notebook.py").read_text()
    assert f'"{name}"' in here or f'"{name}"' in bench

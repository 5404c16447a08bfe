"""Issue 44's catalogue of hard cases on the tiny 12-frame capture (slow: a simulation, SfM and a global
alignment per case): every case ends right or refused, never with a silently wrong placement accepted.
The default-orbit numbers are in docs/tuning/verify.md (``python -m benchmarks.verify_catalogue``)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def tiny_build(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> tuple[Path, Path, Path]:
    from cadalign.sfm import PRESETS, run
    from cadalign.sim.run import simulate
    from cadalign.testing.tiny_scene import write_build_capture

    root = tmp_path_factory.mktemp("catalogue")
    spec = write_build_capture(root / "tiny.toml", effects=["attenuation", "backscatter"], frames=12)
    sim = simulate(spec, root / "sim", video=False, contact_sheet=False)
    run(PRESETS["fast"], sim / "frames", root / "build" / "sfm")
    return root / "build", spec, sim


@pytest.mark.parametrize("case", ["from_truth", "baseline", "turned_180", "mirrored", "twice_as_large", "clutter_70",
                                  "wrong_structure", "small_cad"])
def test_each_hard_case_is_right_or_refused(tiny_build: tuple[Path, Path, Path], case: str) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from benchmarks.verify_catalogue import run_case

    row = run_case(case, *tiny_build)
    assert row.get("verdict") != "SILENTLY WRONG", row
    if case == "from_truth":
        assert row["verdict"] == "correct", row

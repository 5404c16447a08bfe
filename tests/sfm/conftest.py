"""A tiny simulated dive shared by the SfM tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from cadalign.sim.spec import default_scene_path, load_scene


@pytest.fixture(scope="session")
def tiny_dive(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """The first 10 frames, 320x240, of the default scene with all its water effects: consecutive frames 2.9 deg
    apart (0.55 m at 1 frame/s) like a real survey."""
    from cadalign.sim.run import simulate

    scene = default_scene_path()
    assert load_scene(scene).trajectory.fps == 1.0, "the SfM tests' tolerances were measured at 1 frame/s"
    return simulate(scene, tmp_path_factory.mktemp("sim") / "dive", frames=10, resolution=(320, 240),
                    video=False, contact_sheet=False)


@pytest.fixture(scope="session")
def five_frames(tiny_dive: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The first five frames of ``tiny_dive`` (names kept, so ``--gt tiny_dive`` evaluates them)."""
    import shutil

    out = tmp_path_factory.mktemp("five") / "frames"
    out.mkdir()
    for f in sorted((tiny_dive / "frames").glob("*.png"))[:5]:
        shutil.copy(f, out / f.name)
    return out

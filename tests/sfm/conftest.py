"""A tiny simulated dive shared by the SfM tests."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def tiny_dive(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """10 frames, 320x240, of the default scene with all its water effects; the orbit is flown at
    1 frame/s instead of 0.5 so consecutive frames are 2.9 deg apart (0.55 m) like a real survey."""
    from cadalign.sim.run import simulate

    text = (REPO / "datasets" / "scenes" / "default.toml").read_text()
    assert "\nfps = 0.5\n" in text
    scene = tmp_path_factory.mktemp("scene") / "tiny_dive.toml"
    scene.write_text(text.replace("\nfps = 0.5\n", "\nfps = 1.0\n"))
    return simulate(scene, tmp_path_factory.mktemp("sim") / "dive", frames=10, resolution=(320, 240),
                    video=False, contact_sheet=False)

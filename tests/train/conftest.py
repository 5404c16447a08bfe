"""A tiny simulated BOP scene (6 frames, 160x120, no water effects) for the dense training tests."""

from __future__ import annotations

from pathlib import Path

import pytest

from cadalign.sim.run import SCENE_SUBDIR
from cadalign.testing.tiny_scene import simulate_tiny


@pytest.fixture(scope="session")
def tiny_dense(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """The BOP scene folder; its derived time-block split is 4 train, 1 val, 1 test frames."""
    return simulate_tiny(tmp_path_factory.mktemp("dense"), frames=6) / SCENE_SUBDIR


TINY_TOML = """
scale = 0.5
dice_weight = 0.5
[model]
base_channels = 4
{model_extra}
[loop]
steps = {steps}
batch_size = 2
lr = 0.01
checkpoint_every = 2
log_every = 1
[augment]
enabled = {augment}
"""


@pytest.fixture()
def tiny_seg_toml(tmp_path: Path) -> Path:
    """A config file shrinking the seg preset to a CPU toy (3 steps)."""
    p = tmp_path / "seg.toml"
    p.write_text(TINY_TOML.format(model_extra="depth = 3", steps=3, augment="true"))
    return p


@pytest.fixture()
def tiny_depth_toml(tmp_path: Path) -> Path:
    """A config file shrinking the depth preset to a CPU toy (3 steps)."""
    p = tmp_path / "depth.toml"
    p.write_text(TINY_TOML.format(model_extra="levels = 3", steps=3, augment="true").replace("dice_weight = 0.5", ""))
    return p

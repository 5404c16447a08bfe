"""``datasets/scenes/two_pass.toml`` is the default scene flown twice: the same parts, water and lights, and a
trajectory that sees every side twice, from two heights."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from cadalign.sim.spec import check_camera_clearance, load_scene
from cadalign.sim.trajectory import frame_poses

SCENES = Path(__file__).resolve().parents[2] / "datasets" / "scenes"


def test_two_pass_is_the_default_scene_but_for_its_trajectory() -> None:
    default, two = load_scene(SCENES / "default.toml"), load_scene(SCENES / "two_pass.toml")
    assert dataclasses.replace(two, name=default.name, trajectory=default.trajectory) == default
    t = two.trajectory
    assert t.kind == default.trajectory.kind == "orbit" and t.climb_m_per_lap < 0 and t.frames == 128
    check_camera_clearance(two, "two_pass.toml")


def test_two_pass_sees_each_side_twice_from_two_heights() -> None:
    t = load_scene(SCENES / "two_pass.toml").trajectory
    eyes = np.array([p.t for p in frame_poses(t, t.frames)])
    az = np.degrees(np.arctan2(eyes[:, 1], eyes[:, 0])) % 360
    laps = np.floor(np.cumsum(np.r_[0, np.abs(np.diff(np.unwrap(np.radians(az))))]) / (2 * np.pi))
    for side in range(0, 360, 30):  # every 30-degree sector is passed in both laps
        near = np.abs((az - side + 180) % 360 - 180) < 6
        assert {0.0, 1.0} <= set(laps[near]), side
    first, second = np.flatnonzero(laps == 0), np.flatnonzero(laps == 1)
    for k in second:  # the second time 1.5 m lower (climb_m_per_lap), seen from the same side
        j = first[np.argmin(np.abs((az[first] - az[k] + 180) % 360 - 180))]
        assert abs((az[j] - az[k] + 180) % 360 - 180) < 4 and abs(eyes[j, 2] - eyes[k, 2] - 1.5) < 0.2  # jitter_m 0.05

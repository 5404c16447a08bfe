"""The simulated navigation sensor: every frame's pose turned and moved by exactly the amounts asked for."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from cadalign.geometry.rotations import axis_angle_to_matrix, geodesic_angle
from cadalign.infer.track.truth import read_frame_poses
from cadalign.sim.navigation import CAMERAS, true_poses, write_navigation


def _sim(tmp_path: Path) -> Path:
    rng = np.random.default_rng(0)
    frames = {}
    for k in range(4):
        R = axis_angle_to_matrix(rng.normal(size=3))
        frames[f"{k:06d}.png"] = {"R_cam_from_world": R.tolist(), "t_cam_from_world_m": rng.normal(size=3).tolist()}
    (tmp_path / CAMERAS).parent.mkdir(parents=True)
    (tmp_path / CAMERAS).write_text(json.dumps({"frames": frames}))
    return tmp_path


def test_navigation_is_off_by_exactly_the_turn_and_shift_asked_for(tmp_path: Path) -> None:
    sim = _sim(tmp_path)
    path = write_navigation(sim, seed=3, path=tmp_path / "nav.json", turn_deg=5.0, shift_m=0.2)
    nav, truth = read_frame_poses(path, "navigation poses"), true_poses(sim)
    assert sorted(nav) == sorted(truth)
    for name, T in truth.items():
        assert abs(np.degrees(geodesic_angle(nav[name].R, T.R)) - 5.0) < 1e-6
        assert abs(np.linalg.norm(nav[name].inverse().t - T.inverse().t) - 0.2) < 1e-9  # the camera centre moved
    note = json.loads(path.read_text())["note"]
    assert "5 deg" in note and "0.2 m" in note and "seed 3" in note

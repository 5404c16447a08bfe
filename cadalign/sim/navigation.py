"""A simulated navigation sensor: the rough camera pose per frame that an ROV's INS / USBL / DVL gives.

Each frame's navigation pose is its true pose turned by exactly ``turn_deg`` about a random axis and moved by
exactly ``shift_m`` in a random direction, drawn independently per frame (seeded): every frame as rough as the
worst first-frame fix the tracker is asked to start from (``infer --init-pose``, ``--nav``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cadalign.formats.calibration import posed_frames
from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.io import read_json, write_json
from cadalign.types import Rigid3

CAMERAS = Path("gt") / "sim" / "000000" / "cameras.json"


def rough_pose(T_cam_from_world: Rigid3, rng: np.random.Generator, turn_deg: float = 10.0,
               shift_m: float = 0.5) -> Rigid3:
    """``T_cam_from_world`` turned by exactly ``turn_deg`` about a random axis and its camera moved by exactly
    ``shift_m`` (in the camera frame)."""
    ax, d = rng.normal(size=3), rng.normal(size=3)
    turn = Rigid3(axis_angle_to_matrix(np.radians(turn_deg) * ax / np.linalg.norm(ax)), shift_m * d / np.linalg.norm(d))
    return turn @ T_cam_from_world


def true_poses(sim_dir: Path) -> dict[str, Rigid3]:
    """The simulator's true ``T_cam_from_world`` per frame name (``gt/sim/000000/cameras.json``)."""
    return posed_frames(read_json(Path(sim_dir) / CAMERAS))


def navigation_poses(sim_dir: Path, seed: int = 0, turn_deg: float = 10.0, shift_m: float = 0.5) -> dict[str, Rigid3]:
    """Rough navigation poses of every frame of a simulation (module doc); frame ``k`` (in name order) draws
    from seed ``seed + k``, so the first frame's is :func:`first_fix`'s with the same seed."""
    poses = true_poses(sim_dir)
    return {name: rough_pose(poses[name], np.random.default_rng(seed + k), turn_deg, shift_m)
            for k, name in enumerate(sorted(poses))}


def first_fix(sim_dir: Path, frame: str, seed: int = 0, turn_deg: float = 10.0, shift_m: float = 0.5) -> Rigid3:
    """One frame's rough pose from seed ``seed`` (a navigation fix to start the tracker from)."""
    return rough_pose(true_poses(sim_dir)[frame], np.random.default_rng(seed), turn_deg, shift_m)


def write_navigation(sim_dir: Path, seed: int = 0, path: Path | None = None, turn_deg: float = 10.0,
                     shift_m: float = 0.5) -> Path:
    """:func:`navigation_poses` as ``{"frames": {name: T_cam_from_world 4x4}}`` (the format of ``infer --nav``)
    in ``path`` (default ``sim_dir/navigation.json``)."""
    path = Path(sim_dir) / "navigation.json" if path is None else Path(path)
    nav = navigation_poses(sim_dir, seed, turn_deg, shift_m)
    write_json(path, {"frames": {k: T.matrix().tolist() for k, T in nav.items()},
                      "note": f"simulated navigation: each frame's true pose turned exactly {turn_deg:g} deg about a "
                              f"random axis and moved exactly {shift_m:g} m (seed {seed} + frame index)"})
    return path

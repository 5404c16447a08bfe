"""Camera trajectories in the TUM RGB-D format (``timestamp tx ty tz qx qy qz qw``), for evo and other tools.

Each line is one camera's pose **camera-in-world** (``T_world_from_cam``: the camera centre and the rotation that
takes camera axes to world axes), quaternion x, y, z, w, in the units of the poses (SfM units for ``cadalign sfm``,
metres for datasets and simulations). ``timestamp`` is the frame number: the frame file's stem when every stem is
an integer (``000012.png`` -> 12, as the frame dumps of videos are named), else the frame's rank in name order;
a comment line lists the names in order, so a trajectory and its ground truth written here associate exactly
(``evo_ape tum gt.tum est.tum --align --correct_scale``).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from cadalign.errors import InputError
from cadalign.formats.calibration import camera_pose_arrays
from cadalign.geometry.rotations import matrix_to_quaternion
from cadalign.io import write_text

TUM_NAME = "trajectory.tum"
"""File name of the TUM trajectory written beside a ``cameras.json``."""


def frame_stamps(names: list[str]) -> list[float]:
    """Timestamps of frames (see the module doc): integer stems if all are, else ranks in name order."""
    stems = [Path(n).stem for n in names]
    if all(s.isdigit() for s in stems) and len({int(s) for s in stems}) == len(stems):
        return [float(int(s)) for s in stems]
    order = {n: i for i, n in enumerate(sorted(names))}
    return [float(order[n]) for n in names]


def tum_text(names: list[str], R_world_from_cam: np.ndarray, t_world_from_cam: np.ndarray, units: str) -> str:
    """The TUM text of (N,) frames with (N, 3, 3) rotations and (N, 3) centres, sorted by timestamp."""
    stamps = frame_stamps(names)
    q = matrix_to_quaternion(np.asarray(R_world_from_cam, dtype=np.float64).reshape(-1, 3, 3)) if names else \
        np.zeros((0, 4))
    order = np.argsort(stamps, kind="stable")
    lines = ["# cadalign camera trajectory, TUM format: timestamp tx ty tz qx qy qz qw (T_world_from_cam, "
             f"camera-in-world; {units}); timestamp = frame number",
             "# frames: " + " ".join(names[i] for i in order)]
    for i in order:
        t, (w, x, y, z) = np.asarray(t_world_from_cam[i], dtype=np.float64), q[i]
        lines.append(" ".join(repr(float(v)) for v in (stamps[i], *t, x, y, z, w)))
    return "\n".join(lines) + "\n"


def write_cameras_tum(cameras: Mapping[str, Any], path: Path) -> Path:
    """Write the poses of a cameras.json dict (``{"frames": {name: {"R_cam_from_world", "t_cam_from_world_m"}}}``,
    optional ``"units"``) as a TUM trajectory (atomically); frames without a pose are left out."""
    names, R_cw, t_cw = camera_pose_arrays(cameras)
    R_wc = np.swapaxes(R_cw, 1, 2)
    C = -np.einsum("nij,nj->ni", R_wc, t_cw)
    units = {"sfm": "SfM units (arbitrary scale)"}.get(str(cameras.get("units", "m")), "metres")
    return write_text(Path(path), tum_text(names, R_wc, C, units))


def read_tum(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N,) timestamps, (N, 3) positions and (N, 4) quaternions x, y, z, w of a TUM file.

    Raises:
        InputError: a data line without 8 numbers (naming the file and line).
    """
    rows = []
    for k, line in enumerate(Path(path).read_text().splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        try:
            vals = [float(v) for v in parts]
        except ValueError:
            vals = []
        if len(vals) != 8:
            raise InputError(f"{path}:{k}: a TUM line is 'timestamp tx ty tz qx qy qz qw' (8 numbers), got {line!r}; "
                             "fix or regenerate the trajectory file")
        rows.append(vals)
    arr = np.array(rows, dtype=np.float64).reshape(-1, 8)
    return arr[:, 0], arr[:, 1:4], arr[:, 4:8]

"""A region of interest for a CAD that is a small part of the scene: registration uses only the points there.

A ROI file (JSON) holds either a box in the SfM frame, or image clicks round the object in a few frames::

    {"box_sfm": [[xmin, ymin, zmin], [xmax, ymax, zmax]]}
    {"clicks": {"frame_0001.png": [[u, v], [u, v], [u, v], ...], "frame_0040.png": [...]}}

Clicks are polygons in pixels (pixel centres at +0.5, as everywhere in cadalign) of frames by their SfM image
name; a point is kept when it projects inside every clicked polygon (the intersection of their viewing cones).
Projection uses each frame's pinhole ``K`` from ``cameras.json`` without lens distortion: a ROI is a coarse
selection, so click a little outside the object.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cadalign.errors import InputError
from cadalign.formats.calibration import frame_pose
from cadalign.io import read_json


@dataclass(frozen=True)
class Roi:
    """A box ``(2, 3)`` in the SfM frame, or click polygons per frame name (each ``(K, 2)`` pixels)."""

    box_sfm: np.ndarray | None = None
    clicks: dict[str, np.ndarray] | None = None
    source: str = "<roi>"


def read_roi(path: str | Path) -> Roi:
    """Read a ROI file (see the module doc).

    Raises:
        InputError: neither ``box_sfm`` nor ``clicks``, or a malformed box or polygon.
    """
    data = read_json(Path(path))
    if not isinstance(data, dict) or not ({"box_sfm", "clicks"} & set(data)):
        raise InputError(f"{path}: a ROI file needs 'box_sfm' [[xmin, ymin, zmin], [xmax, ymax, zmax]] or 'clicks' "
                         "{frame name: [[u, v], ...]} (see cadalign.align.roi)")
    if "box_sfm" in data:
        box = np.asarray(data["box_sfm"], dtype=np.float64)
        if box.shape != (2, 3) or not np.all(box[1] > box[0]):
            raise InputError(f"{path}: 'box_sfm' must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with max > min, "
                             f"got {data['box_sfm']}")
        return Roi(box_sfm=box, source=str(path))
    clicks = {}
    for name, poly in dict(data["clicks"]).items():
        p = np.asarray(poly, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3:
            raise InputError(f"{path}: the clicks of {name} must be 3 or more [u, v] pixels round the object")
        clicks[str(name)] = p
    if not clicks:
        raise InputError(f"{path}: 'clicks' is empty; click round the object in 2 or more frames")
    return Roi(clicks=clicks, source=str(path))


def roi_mask(points_sfm: np.ndarray, roi: Roi, cameras: dict[str, dict]) -> np.ndarray:
    """(N,) bool: the SfM points inside ``roi``. ``cameras``: the frames of an SfM ``cameras.json``.

    Raises:
        InputError: a clicked frame is not registered in the SfM model.
    """
    pts = np.asarray(points_sfm, dtype=np.float64)
    if roi.box_sfm is not None:
        return np.all((pts >= roi.box_sfm[0]) & (pts <= roi.box_sfm[1]), axis=1)

    keep = np.ones(len(pts), dtype=bool)
    assert roi.clicks is not None
    for name, poly in roi.clicks.items():
        if name not in cameras:
            raise InputError(f"{roi.source}: frame {name!r} is not registered in the SfM model; click in registered "
                             f"frames (see sfm/cameras.json), e.g. {', '.join(sorted(cameras)[:3])}")
        cam = cameras[name]
        x = frame_pose(cam).apply(pts)
        front = x[:, 2] > 0
        uv = (x @ np.reshape(cam["K"], (3, 3)).T)[:, :2] / np.where(front, x[:, 2], 1.0)[:, None]
        contour = poly.astype(np.float32).reshape(-1, 1, 2)
        inside = np.array([cv2.pointPolygonTest(contour, (float(u), float(v)), False) >= 0 for u, v in uv])
        keep &= front & inside
    return keep

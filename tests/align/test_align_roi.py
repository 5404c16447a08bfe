"""Region of interest: a box keeps the points inside it; clicks keep the points inside every clicked outline."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from cadalign.align.roi import read_roi, roi_mask
from cadalign.errors import InputError

K = [[100.0, 0.0, 50.0], [0.0, 100.0, 50.0], [0.0, 0.0, 1.0]]
CAMS = {"a.png": {"R_cam_from_world": np.eye(3).tolist(), "t_cam_from_world_m": [0.0, 0.0, 5.0], "K": K},
        # looking along +x from x = -5 (camera z = world x)
        "b.png": {"R_cam_from_world": [[0, 1, 0], [0, 0, 1], [1, 0, 0]], "t_cam_from_world_m": [0.0, 0.0, 5.0],
                  "K": K}}


def _write(tmp_path: Path, obj: dict) -> Path:
    p = tmp_path / "roi.json"
    p.write_text(json.dumps(obj))
    return p


def test_box_keeps_the_points_inside(tmp_path: Path) -> None:
    pts = np.array([[0.0, 0, 0], [2, 0, 0], [0.5, 0.5, 0.5]])
    roi = read_roi(_write(tmp_path, {"box_sfm": [[-1, -1, -1], [1, 1, 1]]}))
    assert roi_mask(pts, roi, CAMS).tolist() == [True, False, True]


def test_clicks_in_two_views_keep_the_intersection_of_their_cones(tmp_path: Path) -> None:
    # a square of +-10 px round the image centre: +-0.5 m at 5 m in each view
    sq = [[40, 40], [60, 40], [60, 60], [40, 60]]
    roi = read_roi(_write(tmp_path, {"clicks": {"a.png": sq, "b.png": sq}}))
    pts = np.array([[0.0, 0, 0], [0.3, -0.3, 0.2], [0.0, 0, 3.0], [3.0, 0, 0], [0, 3.0, 0]])
    # (0,0,3) and (3,0,0) lie inside one view's cone only; (0,3,0) in neither
    assert roi_mask(pts, roi, CAMS).tolist() == [True, True, False, False, False]


@pytest.mark.parametrize("bad", [{}, {"box_sfm": [[1, 1, 1], [0, 0, 0]]}, {"clicks": {"a.png": [[0, 0], [1, 1]]}}])
def test_malformed_roi_files_name_the_fix(tmp_path: Path, bad: dict) -> None:
    with pytest.raises(InputError, match="roi.json"):
        read_roi(_write(tmp_path, bad))


def test_a_click_in_an_unregistered_frame_is_refused(tmp_path: Path) -> None:
    roi = read_roi(_write(tmp_path, {"clicks": {"nope.png": [[0, 0], [5, 0], [5, 5]]}}))
    with pytest.raises(InputError, match="not registered"):
        roi_mask(np.zeros((2, 3)), roi, CAMS)

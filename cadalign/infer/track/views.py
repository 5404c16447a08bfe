"""The views a lost tracker tries from its own belief, beyond the last pose and the last motion.

Three kinds, each a list of (name, ``T_world_from_cam``) views ranked by a cheap score before the contour fit:
- turned on the spot (:func:`turn_views`): the camera carried on at its last step, then turned about the world
  vertical, as a survey turns at a line's end while the structure is out of view;
- round the structure (:func:`orbit_views`): the last view carried round the vertical through the structure's
  centre, as a cut to another side of an orbit;
- over the ground (:func:`survey_views`): the last height, tilt and roll at any heading and place, ranked by the
  learned colours (:mod:`cadalign.infer.track.survey`).
The first two are ranked by the pan/tilt/roll search's score (:func:`best_views`). ``reachable`` drops views a
navigation pose rules out (:meth:`cadalign.infer.track.tracker.StructureTracker.reachable`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from cadalign.geometry.rotations import axis_angle_to_matrix
from cadalign.infer.track.acquire import candidates
from cadalign.infer.track.config import TrackerConfig
from cadalign.infer.track.edges import EdgeTracker
from cadalign.infer.track.survey import best_by_colour, ground_views
from cadalign.types import Rigid3

Reachable = Callable[[Rigid3], bool]


def round_structure(centre: np.ndarray, deg: float, T_world_from_cam: Rigid3) -> Rigid3:
    """The camera carried ``deg`` degrees round the vertical (world z) through ``centre`` (world frame): the view
    it would have if the structure were turned the other way.

    >>> T = round_structure(np.zeros(3), 90.0, Rigid3(np.eye(3), np.array([1.0, 0.0, 0.0])))
    >>> np.round(T.t, 6).tolist()
    [0.0, 1.0, 0.0]
    """
    R = axis_angle_to_matrix(np.array([0.0, 0.0, np.radians(deg)]))
    return Rigid3(R, centre - R @ centre) @ T_world_from_cam


def best_views(edges: EdgeTracker, gray: np.ndarray, views: list[tuple[str, Rigid3]], cfg: TrackerConfig,
               reachable: Reachable) -> list[tuple[str, Rigid3]]:
    """Of (name, ``T_world_from_cam``) views, the best ``orbit_fits`` by the pan/tilt/roll search's score, as
    (name, ``T_cam_from_world``); views not ``reachable`` are skipped."""
    scored = []
    for name, T_wc in views:
        if not reachable(T_wc):
            continue
        cands = candidates(edges, gray, T_wc, cfg.acquire)
        if cands:
            scored.append((cands[0][0], name, T_wc))
    scored.sort(key=lambda x: -x[0])
    return [(name, T.inverse()) for _, name, T in scored[:cfg.orbit_fits]]


def orbit_views(edges: EdgeTracker, gray: np.ndarray, last: Rigid3, centre: np.ndarray, cfg: TrackerConfig,
                reachable: Reachable) -> list[tuple[str, Rigid3]]:
    """The last view (``last``, ``T_world_from_cam``) turned round the vertical through the structure's centre
    every ``orbit_step_deg`` (a cut to another side), the best by :func:`best_views`."""
    if cfg.orbit_step_deg <= 0:
        return []
    views = [(f"orbit_{a:.0f}", round_structure(centre, a, last))
             for a in np.arange(cfg.orbit_step_deg, 360.0 - 1e-6, cfg.orbit_step_deg)]
    return best_views(edges, gray, views, cfg, reachable)


def turn_views(edges: EdgeTracker, gray: np.ndarray, last: Rigid3, step: np.ndarray | None, lost_frames: int,
               cfg: TrackerConfig, reachable: Reachable) -> list[tuple[str, Rigid3]]:
    """The camera carried on at its last ``step`` (its centre's last step, in its frame before it) and orientation
    over the ``lost_frames``, then turned on the spot about the world vertical (``turn_step_deg``): a survey's turn
    while the structure was out of view. None after ``turn_frames`` lost frames, or without a step."""
    if step is None or cfg.turn_step_deg <= 0 or lost_frames >= cfg.turn_frames:
        return []
    c = last.t + cfg.velocity * (lost_frames + 1) * (last.R @ step)
    views = []
    for a in np.arange(0.0, 360.0 - 1e-6, cfg.turn_step_deg):  # 0: straight on
        R = axis_angle_to_matrix(np.array([0.0, 0.0, np.radians(a)]))
        views.append((f"turn_{a:.0f}", Rigid3(R @ last.R, c)))
    return best_views(edges, gray, views, cfg, reachable)


def survey_views(edges: EdgeTracker, last: Rigid3, box: tuple[np.ndarray, np.ndarray], usual_region: float | None,
                 lost_frames: int, cfg: TrackerConfig, reachable: Reachable) -> list[tuple[str, Rigid3]]:
    """The last view's height, tilt and roll over the whole ground round the structure's world ``box``, any
    heading, best by the learned colours, as (name, ``T_cam_from_world``): a survey's return after turning out of
    view. None on lost frames off ``survey.every``, without a colour frame, or when the track's median region
    support (``usual_region``) is below ``survey.min_region``."""
    rgb = edges.colour_frame
    if rgb is None or cfg.survey.every <= 0 or lost_frames % cfg.survey.every \
            or usual_region is None or usual_region < cfg.survey.min_region:
        return []
    views = [T for T in ground_views(last, *box, cfg.survey) if reachable(T)]
    return [(f"survey_{i}", T.inverse()) for i, T in enumerate(best_by_colour(edges, rgb, views, cfg.survey))]

"""A lost survey's search: the structure looked for over the whole ground, scored by its learned colours.

A survey ROV (a lawnmower over a structure) leaves the structure's view for frames at a time and turns 90 deg at a
line's end while out of view; its dead reckoning from the last tracked frame is then metres and a quarter turn off,
beyond every local search. What it holds is its altitude and its camera's tilt and roll (an ROV flies level at a set
height). So the views searched keep the last tracked frame's height, tilt and roll, and vary the heading (a full
turn) and where the optical axis meets the structure's mid-height plane (a grid over the structure's footprint).
Each view's silhouette is ray cast at a low resolution and scored by the colours the tracker learned on its tracked
frames (:class:`~cadalign.infer.track.region.RegionModel`): the sum over the silhouette of each pixel's log
odds of being the structure's, ``log pf / (1 - pf)``. Colours rank the views where edges cannot (turbid water
blurs the beams' edges, while their paint still differs from the sediment); the best few, apart from each other,
are fitted (each after the tracker's usual pan/tilt/roll search round it), and its tests decide.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from cadalign.geometry.rotations import axis_angle_to_matrix, geodesic_angle
from cadalign.infer.track.edges import EdgeTracker
from cadalign.types import Rigid3


@dataclass(frozen=True)
class SurveyConfig:
    """The lost survey's search over the ground (docs/tuning/tracker.md#a-lost-survey-s58)."""

    every: int = 1
    """While lost with nothing else to restart from, the search runs on every this many lost frames once the
    colours are learned and the turned views found nothing; 0: off."""
    min_region: float = 0.35
    """... and the track's median region support is at least this: colours that hardly tell the parts from their
    surroundings rank views poorly (docs/tuning/tracker.md#a-lost-survey-s58)."""
    step_m: float = 1.0
    """Grid step of the optical axis' meeting point with the structure's mid-height plane, metres (a fit's basin
    reaches about 1.5 m at 8 m range; 1.5 m steps ranked right views 10x lower on clear_lawnmower)."""
    margin_m: float = 2.0
    """The grid covers the structure's footprint widened by this on each side, metres."""
    yaw_step_deg: float = 10.0
    """Heading step, degrees (within a fit's 12 deg basin)."""
    scale: float = 0.0625
    """Image scale of the silhouettes (40x30 at 640x480: ranks as well as 1/8 at a quarter of the rays)."""
    fits: int = 4
    """The best this many views by colour, at least ``apart_m`` / ``apart_deg`` from each other, are fitted (the
    image's edges rank them worse: on clear_lawnmower the right view ranked first or second by colour in frames
    15-19, but not among the four best by the pan/tilt/roll search's edge score)."""
    apart_m: float = 1.5
    """See ``fits``, metres."""
    apart_deg: float = 15.0
    """See ``fits``, degrees."""
    region: float = 0.95
    """The search's best fit needs region support of at least this share of the track's median: a view drawn from
    thousands must look as right as a tracked frame (docs/tuning/tracker.md#a-lost-survey-s58)."""


def ground_views(last: Rigid3, lo: np.ndarray, hi: np.ndarray, cfg: SurveyConfig) -> list[Rigid3]:
    """``T_world_from_cam`` views keeping ``last``'s (``T_world_from_cam``) height and its camera's tilt and roll,
    turned about the world vertical through every ``yaw_step_deg`` and moved so that the optical axis meets the
    plane z = mid-height of the structure's box (``lo``, ``hi``: world corners) on a grid over the box's footprint;
    empty when ``last`` looks level or up (its axis meets no plane below it)."""
    mid = 0.5 * (lo[2] + hi[2])
    axis = last.R[:, 2]
    if axis[2] > -1e-3 or last.t[2] <= mid:  # the camera must look down onto the plane
        return []
    s = (mid - last.t[2]) / axis[2]
    rel = -s * axis  # the camera centre from the point its axis meets the plane
    xs = np.arange(lo[0] - cfg.margin_m, hi[0] + cfg.margin_m + 1e-9, cfg.step_m)
    ys = np.arange(lo[1] - cfg.margin_m, hi[1] + cfg.margin_m + 1e-9, cfg.step_m)
    out = []
    for yaw in np.arange(0.0, 360.0 - 1e-6, cfg.yaw_step_deg):
        Rz = axis_angle_to_matrix(np.array([0.0, 0.0, np.radians(yaw)]))
        R, d = Rz @ last.R, Rz @ rel
        out += [Rigid3(R, np.array([x, y, mid]) + d) for x in xs for y in ys]
    return out


def apart(A: Rigid3, B: Rigid3, cfg: SurveyConfig) -> bool:
    """Whether two camera poses are different views: ``apart_m`` or ``apart_deg`` from each other."""
    return bool(np.linalg.norm(A.t - B.t) >= cfg.apart_m or np.degrees(geodesic_angle(A.R, B.R)) >= cfg.apart_deg)


def best_by_colour(edges: EdgeTracker, rgb: np.ndarray, views: list[Rigid3], cfg: SurveyConfig) -> list[Rigid3]:
    """The best ``cfg.fits`` of ``views`` (``T_world_from_cam``) by the colour score of their silhouettes, apart
    from each other, best first: only views that score above 0 (explain the frame's colours better with the
    structure where they put it than without; a frame without the structure has none); empty without colours."""
    r = edges.renderer(cfg.scale)
    small = cv2.resize(np.ascontiguousarray(rgb), (r.camera.width, r.camera.height), interpolation=cv2.INTER_AREA)
    odds = edges.region.pooled_log_odds(small)
    if odds is None or not views:
        return []
    score = r.silhouettes(views).astype(np.float32) @ odds.ravel().astype(np.float32)
    out: list[Rigid3] = []
    for i in np.argsort(-score, kind="stable"):
        if not score[i] > 0:  # the view explains the colours no better with the structure than without it
            break
        T = views[int(i)]
        if not all(apart(T, C, cfg) for C in out):
            continue
        out.append(T)
        if len(out) >= cfg.fits:
            break
    return out

"""The structure tracker: predict, correct against the image, judge, and restart when lost.

State per frame: ``ok`` (a pose is reported) or ``lost`` (none is). A frame is ``ok`` when the CAD's contours at
the corrected pose find enough support in the image (:class:`~cadalign.infer.track.edges.EdgeFit`). While
lost, every frame tries the restart hypotheses it is given (the detector's, a navigation pose, the last good
pose) and takes the best-supported one that passes the same test.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from cadalign.geometry.rotations import axis_angle_to_matrix, geodesic_angle, matrix_to_axis_angle
from cadalign.infer.track.acquire import candidates
from cadalign.infer.track.config import TrackerConfig
from cadalign.infer.track.edges import EdgeFit, EdgeTracker
from cadalign.infer.track.flow import FlowPredictor
from cadalign.infer.track.region import RegionModel
from cadalign.infer.track.survey import apart
from cadalign.infer.track.views import orbit_views, round_structure, survey_views, turn_views
from cadalign.raycast.core import RenderMesh
from cadalign.types import Camera, Rigid3

log = logging.getLogger(__name__)


class Closest(NamedTuple):
    """A lost frame's best-supported fit that was refused, and why."""

    support: float
    residual_px: float
    region_support: float
    why: str


@dataclass(frozen=True)
class TrackStep:
    """One frame's outcome."""

    index: int
    state: str
    """``ok`` or ``lost``."""
    T_cam_from_world: Rigid3 | None
    """The structure's pose in the camera; None while lost."""
    fit: EdgeFit | None
    source: str
    """What the pose came from: ``track`` (prediction), or the restart hypothesis' name."""
    seconds: float
    restarts_tried: int = 0
    nav_offset: tuple[float, float] | None = None
    """How far the reported camera pose is from the frame's navigation pose (degrees, metres); on a lost frame,
    how far the best fit that passed every test but that one was (None: no navigation pose, or no such fit)."""
    closest: Closest | None = None
    """On a lost frame, its best-supported fit and why it was refused (None: no fit was tried)."""


class StructureTracker:
    """Online tracker of the whole CAD structure (one rigid assembly) in RGB frames.

    ``meshes``: the structure's parts placed in the world frame (ray-cast instances, as
    :meth:`cadalign.sim.structure.Structure.render_meshes` gives). ``camera``: intrinsics and frame size.
    """

    def __init__(self, meshes: list[RenderMesh], camera: Camera, cfg: TrackerConfig | None = None) -> None:
        self.cfg = cfg or TrackerConfig()
        self.edges = EdgeTracker(meshes, camera, self.cfg.edges)
        self.flow = FlowPredictor(camera.K, self.cfg.flow)
        self._last: Rigid3 | None = None  # T_world_from_cam of the last ok frame
        self._prev: Rigid3 | None = None  # and of the ok frame before it (for the velocity)
        self._frames = 0
        self._tracked = 0  # frames accepted (learn_every counts them)
        self.lost = True
        """Whether the last frame was lost (or none was tracked yet)."""
        self._supports: list[float] = []
        self._regions: list[float] = []  # region support of the last tracked frames (kept over losses)
        self._velocity: Rigid3 | None = None  # the last frame-to-frame motion, in the camera frame
        self._step: np.ndarray | None = None  # the camera centre's last step, in the camera frame before it
        self._lost_frames = 0
        self._nav: Rigid3 | None = None  # T_world_from_cam of the current frame's navigation pose, when given
        self._nav_refused: tuple[float, tuple[float, float] | None] | None = None  # this frame's best such fit
        self._closest: Closest | None = None  # this frame's best-supported refused fit
        self._warm = False  # a resumed track (:meth:`resume`) whose colours are not learned yet
        lo = np.min([m.vertices_m.min(axis=0) for m in meshes], axis=0)
        hi = np.max([m.vertices_m.max(axis=0) for m in meshes], axis=0)
        self._centre = (lo + hi) / 2  # the structure's centre, world frame
        self._box = (lo, hi)  # the structure's world box

    @property
    def last_pose(self) -> Rigid3 | None:
        """``T_cam_from_world`` of the last ok frame."""
        return None if self._last is None else self._last.inverse()

    def resume(self, poses: Sequence[Rigid3], supports: Sequence[float] = (), regions: Sequence[float] = (),
               lost_frames: int = 0) -> None:
        """Carry on a track an interrupted run left, as if its frames had been tracked here. ``poses``: the
        ``T_cam_from_world`` of its last tracked frame, after the frame before it when that was tracked too (their
        motion is the prediction's); ``supports``, ``regions``: the edge and region supports of its last tracked
        frames (the track's history); ``lost_frames``: frames lost since the last tracked one. The flow and the
        parts' colours start afresh on the next tracked frame."""
        if not poses:
            return
        self._last = poses[-1].inverse()
        if len(poses) > 1:
            self._velocity = poses[-2] @ self._last
            self._step = self._velocity.t
        self._prev = poses[-2].inverse() if len(poses) > 1 and not lost_frames else None
        self.lost, self._lost_frames = lost_frames > 0, lost_frames
        self._warm = not self.lost  # the next frame learns the parts' colours at its prediction before its fit
        self._supports = list(supports)[-self.cfg.history:]
        self._regions = [r for r in regions if np.isfinite(r)][-self.cfg.history:]

    def good(self, fit: EdgeFit, start: bool = False) -> bool:
        """Whether a fit passes as tracked: enough contours, support and a small residual; a start needs
        ``min_start_support``, a tracked frame also ``relative_support`` of the track's recent support."""
        return self.refusal(fit, start) is None

    def refusal(self, fit: EdgeFit, start: bool = False) -> str | None:
        """Why a fit does not pass as tracked (:meth:`good`), as "test: value against its bound"; None when it
        passes. The best-supported refused fit of a frame is kept for its report (:attr:`TrackStep.closest`)."""
        why = self._refusal(fit, start)
        if why is not None and (self._closest is None or fit.support > self._closest.support):
            self._closest = Closest(fit.support, fit.residual_px, fit.region_support, why)
        return why

    def _refusal(self, fit: EdgeFit, start: bool) -> str | None:
        c = self.cfg
        floor = c.min_start_support if start else max(c.min_support, c.relative_support * self._typical_support())
        if fit.samples < c.min_samples:
            return f"contour samples: {fit.samples} < {c.min_samples}"
        if not fit.support >= floor:
            return f"edge support: {fit.support:.2f} < {floor:.2f}"
        if np.isfinite(fit.region_support):  # the colours are learned: they must agree
            region, usual = c.min_region_support, self._typical_region()
            if usual is not None:
                region = max(region, c.relative_region * usual)
            if not fit.region_support >= region:
                return f"region support: {fit.region_support:.2f} < {region:.2f}"
            if not fit.residual_px <= c.max_residual_region_px:
                return f"residual: {fit.residual_px:.2f} px > {c.max_residual_region_px:.2f}"
        elif not fit.residual_px <= c.max_residual_px:
            return f"residual: {fit.residual_px:.2f} px > {c.max_residual_px:.2f}"
        if not self.near_nav(fit.T_world_from_cam):
            off = self.nav_offset(fit.T_world_from_cam)
            if self._nav_refused is None or fit.support > self._nav_refused[0]:
                self._nav_refused = (fit.support, off)
            return f"navigation: {off[0]:.0f} deg / {off[1]:.1f} m off its pose"
        return None

    def nav_offset(self, T_world_from_cam: Rigid3) -> tuple[float, float] | None:
        """(degrees, metres) between a camera pose and the current frame's navigation pose; None without one."""
        if self._nav is None:
            return None
        return (float(np.degrees(geodesic_angle(T_world_from_cam.R, self._nav.R))),
                float(np.linalg.norm(T_world_from_cam.t - self._nav.t)))

    def near_nav(self, T_world_from_cam: Rigid3) -> bool:
        """Whether a camera pose agrees with the current frame's navigation pose (``nav_max_deg``,
        ``nav_max_m``); True when the frame has none."""
        off = self.nav_offset(T_world_from_cam)
        return off is None or (off[0] <= self.cfg.nav_max_deg and off[1] <= self.cfg.nav_max_m)

    def reachable(self, T_world_from_cam: Rigid3) -> bool:
        """Whether a fit from one of the tracker's own hypotheses at this pose could pass the navigation bound:
        such a fit turns the camera by at most ``acquire.max_turn_deg`` (``own_turn_limit``), so a hypothesis
        turned further than ``nav_max_deg`` plus that from the navigation pose cannot (not worth fitting)."""
        off = self.nav_offset(T_world_from_cam)
        return off is None or not self.cfg.own_turn_limit or \
            off[0] <= self.cfg.nav_max_deg + self.cfg.acquire.max_turn_deg

    def rank(self, fit: EdgeFit) -> float:
        """How restart candidates are ranked: the mean of the edge support over all samples and of the parts'
        own supports (parts with ``rank_min_samples``). The structure's frame holds most contour samples, and
        a lattice frame fits itself turned by its symmetry; its parts then land on nothing (default orbit,
        started by the 300-step detector: support 0.71 at such a pose, 0.75 at the right one, but the parts'
        mean 0.46 against 0.70)."""
        parts = [share for n, share, _ in fit.instance_support.values() if n >= self.cfg.rank_min_samples]
        return 0.5 * (fit.support + (float(np.mean(parts)) if parts else fit.support))

    def _typical_support(self) -> float:
        return float(np.median(self._supports)) if self._supports else 0.0

    def _typical_region(self) -> float | None:
        """The median region support of the last tracked frames; None before any."""
        return float(np.median(self._regions)) if self._regions else None

    def _prediction(self) -> Rigid3 | None:
        if self._last is None:
            return None
        if self._prev is None or self.cfg.velocity <= 0:
            return self._last
        return self._last @ self._motion_over(1)

    def _other_predictions(self) -> list[Rigid3]:
        """When the constant-velocity prediction fails: the last pose, and (``steady_heading``) the last step
        with the last orientation, the step taken in the camera's frame (forward stays forward after a turn) and
        in the world's (``T_world_from_cam``)."""
        assert self._last is not None and self._prev is not None
        out = [self._last]
        if self.cfg.steady_heading:
            world = self._last.t - self._prev.t  # the last step in the world frame
            body = self._last.R @ (self._prev.R.T @ world)  # ... and turned with the camera since
            out = [Rigid3(self._last.R, self._last.t + self.cfg.velocity * d) for d in (body, world)] + out
        return out

    def _motion_over(self, frames: int) -> Rigid3:
        """The last frame-to-frame motion (scaled by ``velocity``) carried on over ``frames`` frames."""
        d = self._velocity if self._velocity is not None else Rigid3.identity()
        w, t = self.cfg.velocity * matrix_to_axis_angle(d.R), self.cfg.velocity * d.t
        out = Rigid3.identity()
        for _ in range(frames):
            out = out @ Rigid3(axis_angle_to_matrix(w), t)
        return out

    def _lost_hypotheses(self, gray: np.ndarray) -> list[tuple[str, Rigid3]]:
        """The tracker's own restart hypotheses while lost: the flow from the last tracked frame, the last motion
        carried on over the frames lost, and the last pose (the turned views are :mod:`cadalign.infer.track.views`)."""
        assert self._last is not None
        out = [("last_pose", self._last.inverse())]
        if self._velocity is not None:
            out.insert(0, ("motion", (self._last @ self._motion_over(self._lost_frames + 1)).inverse()))
        flow = self.flow.predict(gray, self._last) if self.flow.ready else None
        if flow is not None:  # the flow from the last tracked frame, however many frames back
            out.insert(0, ("flow", flow.inverse()))
        return out

    def step(self, gray: np.ndarray, restarts: Sequence[tuple[str, Rigid3]] = (),
             rgb: np.ndarray | None = None, nav: Rigid3 | None = None) -> TrackStep:
        """Track one frame (``gray``: (H, W) float32 0-255). ``restarts``: (name, ``T_cam_from_world``)
        hypotheses, tried in order when there is no track or the prediction fails. ``rgb``: the frame in colour
        (H, W, 3), for the region term (``EdgeTrackConfig.region``); None: edges only. ``nav``: the frame's
        rough navigation pose (``T_cam_from_world``): no pose further from it than ``nav_max_deg`` /
        ``nav_max_m`` is reported, and while lost it is a restart hypothesis besides ``restarts``, followed by
        the tracker's own (which the navigation pose then bounds)."""
        t0 = time.perf_counter()
        self._nav = None if nav is None else nav.inverse()
        self._nav_refused = None
        self._closest = None
        if nav is not None:
            restarts = [*restarts, ("nav", nav)]
        self.edges.colour_frame = rgb if self.cfg.edges.region.enabled else None
        k = self._frames
        self._frames += 1
        tried = 0
        pred = self._prediction()
        flow = self.flow.predict(gray, pred) if pred is not None and self.flow.ready else None
        if pred is not None:
            pred = flow or pred
            if self._warm and rgb is not None and not self.edges.region.ready:
                # a resumed track: a tracked frame's fit uses the parts' colours (without, a small image's coarse
                # level can run off), learned here at the prediction, a frame's motion from the last pose
                self._learn_colours(self.edges.judge(gray, pred))
            self._warm = False
            fit = self.edges.fit(gray, pred, self.cfg.flow_levels if flow is not None else None)
            passed = self.good(fit) and not self.ran_off(pred, fit, "the track", self.cfg.track_turn_deg)
            if passed and fit.support < self.cfg.doubt_support * self._typical_support():
                # passes, but well below the track's usual support: a wrong nearby pose fits that way too, so
                # the search round the prediction decides (the better-supported wins)
                other, n = self._search(gray, pred)
                tried += n
                if other is not None and other.support > fit.support and \
                        not self.ran_off(pred, other, "search", self.cfg.track_turn_deg):
                    fit = other
            if passed:
                # a track resumed after lost frames rests on the tracker's own belief, as its restarts do
                refused, n = self._turned_alike(gray, fit, "the resumed track") if self.lost else (False, 0)
                tried += n
                if not refused:
                    return self._accept(gray, k, fit, "track", t0, tried)
            if self._prev is not None:  # the motion changed: the other predictions, the best-ranked passing one
                tries = [(T, self.edges.fit(gray, T)) for T in self._other_predictions()]
                tried += len(tries)
                fits = [f for T, f in tries
                        if self.good(f) and not self.ran_off(T, f, "a prediction", self.cfg.track_turn_deg)]
                if fits:
                    return self._accept(gray, k, max(fits, key=self.rank), "track", t0, tried)
        best, n = self._best_of(gray, restarts)
        tried += n
        if best is not None and self._last is None:  # a start: searched round again while its support rises,
            climbed, n = self._climb(gray, best[0])  # then fitted again with the colours learned there
            polished, m = self._polish(gray, climbed)
            best, tried = (polished, best[1]), tried + n + m
        # the tracker's own hypotheses: when lost with nothing else to restart from, or when a navigation pose
        # bounds where they may go
        if best is None and self._last is not None and (not restarts or nav is not None):
            best, n = self._own_restart(gray)
            tried += n
        if best is not None:
            self._supports = []  # a restart has no history of support
            return self._accept(gray, k, best[0], best[1], t0, tried)
        if self._prev is not None:
            self._velocity = self._prev.inverse() @ self._last  # kept for the restarts while lost
        self._prev = None  # the last good pose stays the next frame's prediction
        self._lost_frames += 1
        self.lost = True
        return TrackStep(k, "lost", None, None, "", time.perf_counter() - t0, tried,
                         None if self._nav_refused is None else self._nav_refused[1], self._closest)

    def _own_restart(self, gray: np.ndarray) -> tuple[tuple[EdgeFit, str] | None, int]:
        """(the best passing fit of the tracker's own hypotheses, in turn until one passes, and its name; fits
        tried): the last pose and motion, the views turned on the spot, round the structure (every ``orbit_every``
        lost frames) and over the ground (:mod:`cadalign.infer.track.views`)."""
        assert self._last is not None
        best, tried = self._best_of(gray, self._lost_hypotheses(gray), True)
        if best is None:  # turned on the spot while out of view
            views = turn_views(self.edges, gray, self._last, self._step, self._lost_frames, self.cfg, self.reachable)
            best, n = self._best_of(gray, views, True)
            tried += n
        if best is None and self._lost_frames % max(self.cfg.orbit_every, 1) == 0:  # round the structure
            views = orbit_views(self.edges, gray, self._last, self._centre, self.cfg, self.reachable)
            best, n = self._best_of(gray, views, True)
            tried += n
        if best is None:  # a survey's return: anywhere over the ground at the last height
            views = survey_views(self.edges, self._last, self._box, self._typical_region(), self._lost_frames,
                                 self.cfg, self.reachable)
            best, n = self._best_of(gray, views, True, unique=True)
            tried += n
        return best, tried

    def _learn_colours(self, fit: EdgeFit) -> bool:
        """Teach the region term the parts' colours along ``fit``'s contours in the colour frame; False without."""
        rgb = self.edges.colour_frame
        if rgb is None or fit.uv is None or fit.normal is None or fit.sample_instance is None or fit.instance is None:
            return False
        self.edges.region.learn(rgb, fit.uv, fit.normal, fit.sample_instance, fit.instance)
        return True

    def ran_off(self, start: Rigid3, fit: EdgeFit, what: str, limit_deg: float) -> bool:
        """Whether a fit from the tracker's own belief (``start``, ``T_world_from_cam``: a tracked frame's
        prediction, dead reckoning, a turned view) turned the camera further from it than ``limit_deg`` (0: no
        limit): it ran off onto other edges, and is refused."""
        turn = float(np.degrees(geodesic_angle(fit.T_world_from_cam.R, start.R)))
        if limit_deg <= 0 or turn <= limit_deg:
            return False
        log.debug("frame %d: %s refused: its fit turned the camera by %.0f deg (more than %.0f)", self._frames - 1,
                  what, turn, limit_deg)
        return True

    def _best_of(self, gray: np.ndarray, hypotheses: Sequence[tuple[str, Rigid3]], own: bool = False,
                 unique: bool = False) -> tuple[tuple[EdgeFit, str] | None, int]:
        """The best-supported passing (fit, name) of searches from (name, ``T_cam_from_world``) hypotheses,
        and the number of fits tried. ``own``: the tracker's own hypotheses (where it believes the camera is):
        a fit that turned the camera further from one than a pan/tilt search reaches (``acquire.max_turn_deg``)
        ran off it, and is refused (``own_turn_limit``). ``unique`` (a search over the whole ground): refused too
        when another passing fit, apart from the best (``survey.apart_m`` / ``apart_deg``), ranks within
        ``unique_margin`` of it, or when the best's region support is below ``survey.region`` of the track's usual."""
        passing: list[tuple[EdgeFit, str]] = []
        tried = 0
        for name, T_cw in hypotheses:
            if own and not self.reachable(T_cw.inverse()):
                continue
            fit, n = self._search(gray, T_cw.inverse())
            tried += n
            if fit is not None and own and self.cfg.own_turn_limit and self.ran_off(
                    T_cw.inverse(), fit, f"restart from {name}", self.cfg.acquire.max_turn_deg):
                continue
            if fit is not None:
                passing.append((fit, name))
        if not passing:
            return None, tried
        best = max(passing, key=lambda p: self.rank(p[0]))  # the first of equals
        if unique and any(apart(f.T_world_from_cam, best[0].T_world_from_cam, self.cfg.survey)
                          and self.rank(f) > self.rank(best[0]) - self.cfg.unique_margin for f, _ in passing):
            log.info("frame %d: %s refused: a view elsewhere fits as well", self._frames - 1, best[1])
            return None, tried
        usual = self._typical_region()
        if unique and usual is not None and not best[0].region_support >= self.cfg.survey.region * usual:
            log.info("frame %d: %s refused: region support %.2f below the track's usual %.2f", self._frames - 1,
                     best[1], best[0].region_support, usual)
            return None, tried
        if own:
            refused, n = self._turned_alike(gray, best[0], best[1])
            tried += n
            if refused:
                return None, tried
        return best, tried

    def _climb(self, gray: np.ndarray, fit: EdgeFit) -> tuple[EdgeFit, int]:
        """(a start's fit searched round again, up to ``start_climbs`` times, while the best passing fit's support
        rises by more than ``climb_gain``; fits tried): the search from a rough fix can stop on a nearby pose."""
        tried = 0
        for _ in range(self.cfg.start_climbs):
            other, n = self._search(gray, fit.T_world_from_cam)
            tried += n
            if other is None or not other.support > fit.support + self.cfg.climb_gain:
                break
            fit = other
        return fit, tried

    def _polish(self, gray: np.ndarray, fit: EdgeFit) -> tuple[EdgeFit, int]:
        """(a start's fit fitted again with the parts' colours learned at it, when that finds more edges by
        ``start_margin``, as a search's candidate must beat its hypothesis' own fit; fits tried): the start's search
        fits edges alone, and the region term widens the fit's basin (``polish_start``). Tried aside: the track learns
        the colours at the fit it keeps, and a second fit not kept leaves nothing behind."""
        if not self.cfg.polish_start or self.edges.region.ready:
            return fit, 0
        before = self.edges.snapshot()
        self.edges.region = RegionModel(before[0].cfg)
        better = False
        try:
            if not self._learn_colours(fit):
                return fit, 0
            again = self._restart_fit(gray, fit.T_world_from_cam)
            better = self.good(again, start=True) and again.support > fit.support + self.cfg.start_margin and \
                not self.ran_off(fit.T_world_from_cam, again, "the start's second fit", self.cfg.acquire.max_turn_deg)
        finally:  # the colours as before (the track learns them at the fit it keeps); the last judged render the
            # kept fit's, which the next frame may carry
            carried = self.edges.snapshot()[1] if better else before[1]
            self.edges.restore((before[0], carried))
        # its region support rests on colours from this frame: read again on accepting, as the first frame's is
        return (replace(again, region_support=float("nan")), 1) if better else (fit, 1)

    def _turned_alike(self, gray: np.ndarray, fit: EdgeFit, name: str) -> tuple[bool, int]:
        """(whether a pose the tracker found by itself, with no navigation pose to bound it, is refused: the view
        turned a quarter, a half or three quarters round the structure's vertical through its centre passes and
        ranks within ``unique_margin`` of it; fits tried)."""
        if self._nav is not None or self.cfg.unique_margin <= 0:
            return False, 0
        tried = 0
        for a in (90, 180, 270):
            alt = self._restart_fit(gray, round_structure(self._centre, a, fit.T_world_from_cam))
            tried += 1
            if self.good(alt, start=True) and self.rank(alt) > self.rank(fit) - self.cfg.unique_margin:
                log.info("frame %d: %s refused: the structure turned %d deg round its vertical fits as well (rank "
                         "%.2f against %.2f); give --nav or a detector to tell the views apart", self._frames - 1,
                         name, a, self.rank(alt), self.rank(fit))
                return True, tried
        return False, tried

    def _restart_fit(self, gray: np.ndarray, T_world_from_cam: Rigid3) -> EdgeFit:
        """A restart's contour fit: ``restart_levels``, every ``restart_fit_step``-th sample."""
        return self.edges.fit(gray, T_world_from_cam, self.cfg.restart_levels, self.cfg.restart_fit_step)

    def _search(self, gray: np.ndarray, T_world_from_cam: Rigid3) -> tuple[EdgeFit | None, int]:
        """The best-supported passing fit from a rough pose: the pose itself and the candidates of the
        pan/tilt/roll search round it, in up to ``acquire_rounds`` searches (each round the best fit of the
        one before when none passed); (None, tries) when none passes. The pose's own fit is kept unless a
        candidate beats its support by ``start_margin`` (clutter lends wrong candidates support too)."""
        start, tried = T_world_from_cam, 0
        for _ in range(max(self.cfg.acquire_rounds, 1)):
            own = self._restart_fit(gray, start)
            tried += 1
            best = own if self.good(own, start=True) else None
            top = own
            for _, T_wc in candidates(self.edges, gray, start, self.cfg.acquire):
                tried += 1
                fit = self._restart_fit(gray, T_wc)
                if self.good(fit, start=True) and (best is None or self.rank(fit) > self.rank(best) + (
                        self.cfg.start_margin if best is own else 0.0)):
                    best = fit
                if fit.support > top.support:
                    top = fit
            if best is not None:
                return best, tried
            start = top.T_world_from_cam
        return None, tried

    def _accept(self, gray: np.ndarray, k: int, fit: EdgeFit, source: str, t0: float, tried: int) -> TrackStep:
        # the motion from the frame before is a velocity when that frame was tracked too (also when this one
        # needed a restart: a survey's 80 px steps outrun the fit's basin, yet its speed is steady)
        self._prev = self._last if source == "track" or not self.lost else None
        self._last = fit.T_world_from_cam
        if self._prev is not None:
            self._velocity = self._prev.inverse() @ self._last
            self._step = self._velocity.t
        self._lost_frames = 0
        self.lost = False
        self._supports = (self._supports + [fit.support])[-self.cfg.history:]
        if np.isfinite(fit.region_support):
            self._regions = (self._regions + [fit.region_support])[-self.cfg.history:]
        if fit.depth_m is not None and fit.instance is not None:
            self.flow.remember(gray, fit.depth_m, fit.instance, fit.T_world_from_cam)
        self._tracked += 1
        learn = not self.edges.region.ready or self._tracked % max(self.cfg.learn_every, 1) == 0
        if learn and self._learn_colours(fit):
            if not np.isfinite(fit.region_support):  # the first frame: read with the colours it just taught
                fit = self.edges.with_region(fit)  # (for the parts' check only: not in the track's history)
        return TrackStep(k, "ok", fit.T_world_from_cam.inverse(), fit, source, time.perf_counter() - t0, tried,
                         self.nav_offset(fit.T_world_from_cam))

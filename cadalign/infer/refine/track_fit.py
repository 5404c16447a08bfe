"""Multi-frame refit of a static part's world pose: one ICP of the CAD to the masked depth of all its detections.

Per frame, a part seen from 7-15 m shows a few dozen depth points: a thin cylinder (a hot stab) fits anywhere along
its axis and either end first, and a small valve's handle fits a quarter turn off. The robust mean of such per-frame
fits keeps their common mistake. The same part seen from the whole orbit, its points moved to the world frame by
the frames' camera poses, fixes all of it. So after the video, a track's world pose is fitted again to the union of
its detections' masked depth points, by point-to-plane ICP in the world frame (a point's facing test uses its own
camera's centre), from its fused pose and from a grid of starts: the fused rotation turned by each of the 24
rotations of the cube, each with a few model points (the centroid and farthest-point samples) put on the points'
median. All starts run a few ICP iterations on a subsample; the fused pose and the best few are then moved along
the model's principal axes and run again (``hops``: ICP slides along a cylinder into the nearest minimum); the best
few and the fused start run to convergence on all points. The best fit (mean data -> model distance, each capped at
a tenth of the diameter) wins; fits within ``tie_rel`` of it are ties, and of those the one that turns least from the
fused pose (symmetry-aware) wins. With the track's views, the fits that explain the points nearly as well are first
compared by what the points cannot show: where the model would cover background or leave the masks unexplained
(``view_pick_rel``).

A track's model was chosen on its first, smallest views. With ``choose_model``, every model of its class is fitted the
same way and the one that agrees best with the track's views is kept (:func:`pick_model`); the chosen fit is then
turned, where the points cannot tell, to agree better with the views (:func:`turn_by_view`).

Two tracks on one part (a detection given another model of the class starts a second track) are found the same way:
one's refitted pose explains the other's points (:func:`duplicates`).
"""

from __future__ import annotations

import functools
import itertools
import math
from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from cadalign.cad.symmetry import Symmetry
from cadalign.geometry.rotations import axis_angle_to_matrix, orthonormalize
from cadalign.infer.config import RefitConfig
from cadalign.infer.model_geom import ModelGeometry
from cadalign.infer.pose_math import canonicalize
from cadalign.infer.refine.depth_icp import FIT_CAP, depth_fit
from cadalign.infer.refine.half_turn import view_disagreement_parts
from cadalign.infer.refine.refine_math import clamp_step, huber_weights
from cadalign.metrics.pose import rotation_error_deg
from cadalign.types import Rigid3


@dataclass(frozen=True)
class RefitResult:
    """The refitted pose, its fit and the fused pose's fit after its own ICP (mean capped distance, m)."""

    T_world_from_obj: Rigid3
    fit_m: float
    fused_fit_m: float
    starts: int


@dataclass(frozen=True)
class TrackView:
    """One detection's view, cropped around its mask: what :func:`view_score` compares a model's pose with."""

    K: np.ndarray
    """(3, 3) intrinsics of the crop."""
    T_cam_from_world: Rigid3
    mask: np.ndarray
    """(h, w) bool, the detection's mask in the crop."""
    depth_m: np.ndarray
    """(h, w) observed depth in the crop, metres (not finite or <= 0: none)."""

    @functools.cached_property
    def mask_depth_m(self) -> float | None:
        """Median observed depth over the mask (None without any): computed once, every pose scored against it."""
        z = self.depth_m[self.mask]
        z = z[np.isfinite(z) & (z > 0)]
        return float(np.median(z)) if len(z) else None

    @staticmethod
    def crop(K: np.ndarray, T_world_from_cam: Rigid3, mask: np.ndarray, depth_m: np.ndarray,
             pad: float) -> TrackView | None:
        """The view of a detection's ``mask`` (H, W) in a frame of depth ``depth_m`` (H, W): its box grown by
        ``pad`` times its longer side (+ 8 px) on each side, clipped to the frame; None for an empty mask."""
        rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
        if not len(rows):
            return None
        g = int(np.ceil(pad * max(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1))) + 8
        H, W = mask.shape
        y0, y1 = max(int(rows[0]) - g, 0), min(int(rows[-1]) + 1 + g, H)
        x0, x1 = max(int(cols[0]) - g, 0), min(int(cols[-1]) + 1 + g, W)
        Kc = np.array(K, float)
        Kc[0, 2] -= x0
        Kc[1, 2] -= y0
        return TrackView(Kc, T_world_from_cam.inverse(), mask[y0:y1, x0:x1].copy(),
                         np.asarray(depth_m, np.float32)[y0:y1, x0:x1].copy())


@dataclass
class TrackPoints:
    """Masked depth points per track, in the world frame, with the centre of the camera that saw each (and, with
    ``choose_model``, each detection's cropped view)."""

    cfg: RefitConfig
    _points: dict = field(default_factory=lambda: defaultdict(list))
    _views: dict = field(default_factory=lambda: defaultdict(list))
    _offered: Counter = field(default_factory=Counter)
    _rng: np.random.Generator = field(init=False)
    _view_rng: np.random.Generator = field(init=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.cfg.seed)
        self._view_rng = np.random.default_rng(self.cfg.seed + 1)

    def add(self, track_id: int, Q_cam: np.ndarray, T_world_from_cam: Rigid3, view: TrackView | None = None) -> None:
        """Keep up to ``points_per_frame`` of one detection's camera-frame points ``Q_cam`` (N, 3), and its view."""
        Q = np.asarray(Q_cam, float).reshape(-1, 3)
        if len(Q) > self.cfg.points_per_frame:
            Q = Q[np.sort(self._rng.choice(len(Q), self.cfg.points_per_frame, replace=False))]
        if len(Q):
            self._points[track_id].append((T_world_from_cam.apply(Q), T_world_from_cam.t))
        if view is not None:  # reservoir sampling: each of the track's views kept with the same chance
            kept, n = self._views[track_id], self._offered[track_id]
            self._offered[track_id] += 1
            if len(kept) < self.cfg.max_views:
                kept.append(view)
            elif (j := int(self._view_rng.integers(n + 1))) < self.cfg.max_views:
                kept[j] = view

    def views(self, track_id: int) -> list[TrackView]:
        """The kept views of a track's detections."""
        return list(self._views.get(track_id, []))

    def frames(self, track_id: int) -> int:
        """Detections of a track that gave points."""
        return len(self._points.get(track_id, []))

    def of(self, track_id: int) -> tuple[np.ndarray, np.ndarray]:
        """(points (N, 3), camera centres (N, 3)) of a track, empty when it has none."""
        parts = self._points.get(track_id, [])
        if not parts:
            return np.zeros((0, 3)), np.zeros((0, 3))
        P = np.concatenate([p for p, _ in parts])
        C = np.concatenate([np.repeat(c[None], len(p), 0) for p, c in parts])
        return P, C


def icp_world(geom: ModelGeometry, starts: Sequence[Rigid3], P: np.ndarray, C: np.ndarray, iters: int,
              huber_m: float) -> list[Rigid3]:
    """Point-to-plane ICP of the model from each pose of ``starts`` (world from object) to world points ``P``
    (N, 3), each seen from the camera centre in ``C`` (N, 3): a model sample facing away from a point's camera
    cannot be its match. Correspondences within a tenth of the diameter, within half of it while fewer than half
    the points pair; Huber-weighted; the starts run side by side, each until its step is negligible, it has
    fewer than 6 matches, or ``iters``. Returns the poses in the order of ``starts``."""
    d = geom.diameter_m
    R = np.stack([T.R for T in starts]).astype(float)
    t = np.stack([T.t for T in starts]).astype(float)
    active = np.ones(len(starts), bool)
    for _ in range(iters):
        idx = np.flatnonzero(active)
        if not len(idx):
            break
        Ra, ta = R[idx], t[idx]
        q = np.einsum("sji,snj->sni", Ra, P[None] - ta[:, None])  # the points in each start's model frame
        dist, j = geom.tree.query(q.reshape(-1, 3), distance_upper_bound=0.5 * d)
        dist, j = dist.reshape(q.shape[:2]), j.reshape(q.shape[:2])
        ok = dist < 0.1 * d
        wide = ok.mean(1) < 0.5  # far from converged: widen the gate until most points pair up
        ok[wide] = np.isfinite(dist[wide])
        j = np.where(ok, j, 0)
        p = np.einsum("sij,snj->sni", Ra, geom.samples[j]) + ta[:, None]
        n = np.einsum("sij,snj->sni", Ra, geom.sample_normals[j])
        ok &= np.einsum("sni,sni->sn", n, p - C[None]) < 0
        r = np.einsum("sni,sni->sn", n, p - P[None])
        J = np.concatenate([np.cross(p - ta[:, None], n), n], axis=2)
        w = huber_weights(r, huber_m) * ok
        H = np.einsum("sn,sni,snj->sij", w, J, J)
        g = np.einsum("sn,sni,sn->si", w, J, r)
        # a cylinder's spin is free: damped, relative to the mean diagonal
        H += 1e-3 * np.maximum(np.trace(H, axis1=1, axis2=2) / 6, 1e-12)[:, None, None] * np.eye(6)
        enough = ok.sum(1) >= 6
        step = np.zeros((len(idx), 6))
        step[enough] = -np.linalg.solve(H[enough], g[enough][..., None])[..., 0]
        step = clamp_step(step, d)
        R[idx] = axis_angle_to_matrix(step[:, :3]) @ Ra
        t[idx] = ta + step[:, 3:]
        small = (np.linalg.norm(step[:, :3], axis=1) < 1e-5) & (np.linalg.norm(step[:, 3:], axis=1) < 1e-5 * d)
        active[idx[small | ~enough]] = False
    return [Rigid3(orthonormalize(Rk), tk) for Rk, tk in zip(R, t, strict=True)]


def explained(geom: ModelGeometry, T: Rigid3, P: np.ndarray, tol_m: float) -> float:
    """Share of the points ``P`` (N, 3) within ``tol_m`` of the model surface at ``T`` (0 for no points)."""
    if len(P) == 0:
        return 0.0
    return float(np.mean(_distances_within(geom, T, P, tol_m) <= tol_m))


def closeness(geom: ModelGeometry, T: Rigid3, P: np.ndarray, tol_m: float) -> float:
    """Mean over the points ``P`` (N, 3) of ``1 - d / tol_m``, ``d`` a point's distance to the nearest of the model's
    surface samples at ``T`` (0 from ``tol_m`` on; 0 for no points): :func:`explained`'s share, graded, so a pose the
    points hug scores above one they merely lie within ``tol_m`` of (the share averaged over tolerances up to
    ``tol_m``). Points on the surface score below 1 by the samples' spacing."""
    if len(P) == 0:
        return 0.0
    return float(np.mean(np.clip(1.0 - _distances_within(geom, T, P, tol_m) / tol_m, 0.0, 1.0)))


def _distances_within(geom: ModelGeometry, T: Rigid3, P: np.ndarray, tol_m: float) -> np.ndarray:
    """Each point's distance to the nearest of the model's surface samples at ``T``; inf beyond ``tol_m``."""
    return geom.tree.query(T.inverse().apply(P), distance_upper_bound=tol_m)[0]


@dataclass(frozen=True)
class ViewScoring:
    """How :func:`view_score` counts the pixels where a pose disagrees with a track's views."""

    tol_m: float
    """Depth tolerance: a model pixel is seen through when the view's depth lies farther than this behind it."""
    band_px: float
    """Pixels within this distance of an outline are not counted."""
    near_m: float
    """Mask pixels the model leaves unexplained count only within this of the mask's median depth."""
    mask_weight: float = 1.0
    """Weight of an unexplained mask pixel against a seen-through one."""


def view_score(geom: ModelGeometry, T_world_from_obj: Rigid3, views: Sequence[TrackView],
               scoring: ViewScoring) -> float:
    """Pixels, summed over ``views``, where the model at ``T_world_from_obj`` disagrees with the view
    (:func:`cadalign.infer.refine.half_turn.view_disagreement`): seen through, plus ``scoring.mask_weight`` times
    the mask pixels it leaves unexplained (see :class:`ViewScoring`)."""
    total = 0.0
    for v in views:
        near = None if v.mask_depth_m is None else (v.mask_depth_m, scoring.near_m)
        h, w = v.mask.shape
        seen, unexplained = view_disagreement_parts(geom, v.T_cam_from_world @ T_world_from_obj, v.K, v.mask,
                                                    v.depth_m, scoring.tol_m, (0, 0, w, h), scoring.band_px, near)
        total += seen + scoring.mask_weight * unexplained
    return total


def turn_by_view(geom: ModelGeometry, T: Rigid3, P: np.ndarray, views: Sequence[TrackView], steps_deg: Sequence[float],
                 scoring: ViewScoring, tie_rel: float, *, max_moves: int = 8, C: np.ndarray | None = None,
                 icp_iters: int = 0, huber_m: float = 0.005, min_gain: float = 0.0) -> Rigid3:
    """``T`` turned about the model's axes through its centroid, by each of ``steps_deg`` in turn, while a turn lowers
    :func:`view_score` over ``views`` and keeps :func:`~cadalign.infer.refine.depth_icp.depth_fit` of the points ``P``
    (N, 3) within ``tie_rel`` of ``T``'s (at most ``max_moves`` turns per step). With ``icp_iters`` and the points'
    camera centres ``C``, each turned pose is first fitted again to the points by that many ICP iterations (its
    position follows the turn). ``T`` itself unless the score falls by more than ``min_gain`` in all."""
    return _turn(geom, T, P, views, steps_deg, scoring, tie_rel, max_moves=max_moves, C=C, icp_iters=icp_iters,
                 huber_m=huber_m, min_gain=min_gain)[0]


def _turn(geom: ModelGeometry, T: Rigid3, P: np.ndarray, views: Sequence[TrackView], steps_deg: Sequence[float],
          scoring: ViewScoring, tie_rel: float, *, max_moves: int, C: np.ndarray | None, icp_iters: int,
          huber_m: float, min_gain: float) -> tuple[Rigid3, float]:
    """:func:`turn_by_view` and the view score of the pose it returns (0 without views or points)."""
    if not views or not len(P):
        return T, 0.0
    c = geom.samples.mean(0)
    fit_max = depth_fit(geom, T, P) * (1.0 + tie_rel)
    best, best_v = T, view_score(geom, T, views, scoring)
    start_v = best_v
    for step in steps_deg:
        for _ in range(max_moves):
            centre = best.apply(c[None])[0]
            turned = []
            for axis, sign in itertools.product(np.eye(3), (1.0, -1.0)):
                R = best.R @ axis_angle_to_matrix(sign * math.radians(step) * axis)
                turned.append(Rigid3(R, centre - R @ c))
            if icp_iters and C is not None:
                turned = icp_world(geom, turned, P, C, icp_iters, huber_m)
            cands = [(view_score(geom, T2, views, scoring), i, T2)
                     for i, T2 in enumerate(turned) if depth_fit(geom, T2, P) <= fit_max]
            top = min(cands, key=lambda x: (x[0], x[1]), default=None)
            if top is None or top[0] >= best_v:
                break
            best_v, _, best = top
    return (best, best_v) if start_v - best_v > min_gain else (T, start_v)


def turn_track(geom: ModelGeometry, T: Rigid3, P: np.ndarray, C: np.ndarray, views: Sequence[TrackView],
               cfg: RefitConfig, scoring: ViewScoring) -> Rigid3:
    """A track's refitted pose turned by its views (``cfg.view_turns_deg``): :func:`turn_by_view` on the final ICP's
    points (``cfg.max_points`` of ``P`` (N, 3) seen from ``C``), once per ``cfg.turn_icp_iters``; the result with the
    lowest :func:`view_score` wins (ties: the first). ``T`` without turns or views."""
    P, C = _at_most(np.asarray(P, float).reshape(-1, 3), np.asarray(C, float).reshape(-1, 3), cfg.max_points,
                    np.random.default_rng(cfg.seed))
    out = [_turn(geom, T, P, views, cfg.view_turns_deg, scoring, cfg.tie_rel, max_moves=8, C=C, icp_iters=n,
                 huber_m=cfg.huber_m, min_gain=cfg.turn_min_px * len(views)) for n in cfg.turn_icp_iters]
    return min(out, key=lambda x: x[1])[0] if out else T


def _at_most(P: np.ndarray, C: np.ndarray, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` of the points ``P`` and their camera centres ``C``, drawn by ``rng`` (all when there are no more)."""
    if len(P) <= n:
        return P, C
    pick = rng.choice(len(P), n, replace=False)
    return P[pick], C[pick]


def pick_model(fits: dict[int, Rigid3], geoms: dict[int, ModelGeometry], P: np.ndarray, own: int, margin: float,
               views: Sequence[TrackView] = (), tol_rel: float = 0.1, band_px: float = 0.0,
               min_px: float = 0.0, mask_weight: float = 1.0) -> int:
    """The CAD model whose fitted pose (``fits``: model id -> world pose) agrees best with the track.

    Without ``views``: the smallest :func:`cadalign.infer.refine.depth_icp.depth_fit` of the points ``P`` (N, 3), capped
    at a tenth of the smallest candidate's diameter for all (a big model's looser cap does not favour it). With
    ``views``: the fewest pixels of :func:`view_score` (depth tolerance ``tol_rel`` of each model's diameter,
    mask pixels within the largest candidate's diameter of the median masked depth count for all). ``own`` (the
    track's model) stays unless another scores better by more than ``margin`` (a fraction of its score) and, with
    views, by more than ``min_px`` pixels per view."""
    if not fits:
        raise ValueError("pick_model needs at least one fitted model")
    score: dict[int, float]
    if views:
        near = max(geoms[k].diameter_m for k in fits)
        score = {k: view_score(geoms[k], T, views, ViewScoring(tol_rel * geoms[k].diameter_m, band_px, near,
                                                                mask_weight)) for k, T in fits.items()}
    else:
        cap = 0.1 * min(geoms[k].diameter_m for k in fits)
        score = {k: depth_fit(geoms[k], T, P, cap) for k, T in fits.items()}
    best = min(score, key=lambda k: (score[k], k))
    if own in score and score[own] <= max(score[best] * (1.0 + margin), score[best] + min_px * len(views)):
        return own
    return best


@dataclass(frozen=True)
class FittedTrack:
    """A track after the refit, for :func:`duplicates`."""

    track_id: int
    label: int
    world: int
    frames: int
    geom: ModelGeometry
    T_world_from_obj: Rigid3
    points: np.ndarray
    obj_id: int | None = None
    """The CAD model fitted (with ``choose_model``, maybe not the track's own)."""
    fit_m: float = math.nan
    """The refit's fit (:attr:`RefitResult.fit_m`: the points' mean capped distance to the fitted model, m)."""

    @property
    def fit_rel(self) -> float:
        """How well the fitted model explains the track's points: ``fit_m`` over
        :func:`~cadalign.infer.refine.depth_icp.depth_fit`'s cap (0: on the surface; 1: every point a cap or more
        away)."""
        return self.fit_m / (FIT_CAP * self.geom.diameter_m)


def duplicates(tracks: Sequence[FittedTrack], cfg: RefitConfig) -> dict[int, int]:
    """``{track id: the track id it duplicates}`` (``cfg.dup_share``).

    Two tracks of one class and world, their models within reach of each other, are one part when one's pose
    explains the other's points at least ``dup_share`` times as well as the other's own pose does (points within
    ``dup_tol`` of the smaller model's diameter). Of the two, the one whose pose lies closer to both tracks' points
    is kept (:func:`closeness` within that tolerance; ties: more detections, then the lower id). Tracks are visited
    by detections, most first.

    Closeness, not the share within the tolerance: a track whose pose is a few cm off along a long part's axis, its
    own points loose (a mask spilling off the part), explains nearly all of a right track's points within the
    tolerance and more of its own, and won on the share. Default orbit, 33 held-out frames, true depth, ``accurate``
    with training/infer_hot_stab_03.toml, improved seed 2 7400 steps (session 29's networks): the share kept a hot
    stab track 8 cm / 27 deg off (fit 18.5 mm) over two right ones (fit 4.5 and 3.6 mm; closeness 0.68 vs 0.54 and
    0.62 vs 0.51). Share -> closeness, hot stab F1 and fused t / R means: that network 0.842, 0.032 m / 6.8 deg ->
    1.000, 0.0006 m / 0.19 deg; seed 0 7400 steps 1.000, 0.0043 m / 1.3 deg -> 1.000, 0.0008 m / 0.8 deg; F1 of
    five more networks and of all seven on a second dive (datasets/scenes/two_pass.toml) unchanged."""
    out: dict[int, int] = {}
    if cfg.dup_share <= 0:
        return out
    order = sorted(tracks, key=lambda a: (-a.frames, a.track_id))
    for i, a in enumerate(order):
        for b in order[:i]:
            if b.track_id in out or a.track_id in out or not _same_part(a, b, cfg):
                continue
            tol = cfg.dup_tol * min(a.geom.diameter_m, b.geom.diameter_m)
            both = np.concatenate([a.points, b.points])
            if closeness(a.geom, a.T_world_from_obj, both, tol) > closeness(b.geom, b.T_world_from_obj, both, tol):
                out[b.track_id] = a.track_id
                out = {k: (a.track_id if v == b.track_id else v) for k, v in out.items()}
            else:
                out[a.track_id] = b.track_id
    return out


def _same_part(a: FittedTrack, b: FittedTrack, cfg: RefitConfig) -> bool:
    """Whether ``b``'s pose explains ``a``'s points, or ``a``'s ``b``'s, nearly as well as their own (same class and
    world, centres within half the sum of the diameters)."""
    centre = [x.T_world_from_obj.apply(x.geom.samples.mean(0)[None])[0] for x in (a, b)]
    if (a.label != b.label or a.world != b.world
            or np.linalg.norm(centre[0] - centre[1]) > 0.5 * (a.geom.diameter_m + b.geom.diameter_m)):
        return False
    tol = cfg.dup_tol * min(a.geom.diameter_m, b.geom.diameter_m)
    for x, y in ((a, b), (b, a)):
        other = explained(y.geom, y.T_world_from_obj, x.points, tol)
        if other > 0 and other >= cfg.dup_share * explained(x.geom, x.T_world_from_obj, x.points, tol):
            return True
    return False


@functools.cache
def _cube_rotations() -> np.ndarray:
    """The 24 rotations of the cube (signed permutation matrices of determinant +1)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            M[range(3), perm] = signs
            if np.linalg.det(M) > 0:
                out.append(M)
    return np.stack(out)


def _distinct(Rs: np.ndarray, symmetry: Symmetry | None) -> list[np.ndarray]:
    """The rotations of ``Rs`` (N, 3, 3) that the part's symmetry does not make equal to an earlier one (a
    cylinder's 24 cube turns are 6 directions of its axis)."""
    out: list[np.ndarray] = []
    for R in Rs:
        if all(rotation_error_deg(R, Q, symmetry) > 1.0 for Q in out):
            out.append(R)
    return out


def _anchors(geom: ModelGeometry, n: int) -> np.ndarray:
    """The samples' centroid, then ``n - 1`` farthest-point samples."""
    S = geom.samples
    out = [S.mean(0)]
    dist = np.linalg.norm(S - out[0], axis=1)
    for _ in range(n - 1):
        k = int(np.argmax(dist))
        out.append(S[k])
        dist = np.minimum(dist, np.linalg.norm(S - S[k], axis=1))
    return np.stack(out)


def refit_world_pose(geom: ModelGeometry, T_fused: Rigid3, P: np.ndarray, C: np.ndarray, cfg: RefitConfig,
                     symmetry: Symmetry | None = None, views: Sequence[TrackView] = (),
                     scoring: ViewScoring | None = None) -> RefitResult | None:
    """The world pose of a static part fitted to all its points ``P`` (N, 3) seen from ``C`` (N, 3), searched from
    ``T_fused`` and a grid of starts (module doc); None with fewer than ``cfg.min_points`` points. With ``views``
    and ``scoring`` the final fits are also compared by their views (``cfg.view_pick_rel``).

    The result is the symmetric equivalent nearest ``T_fused`` (a spun cylinder keeps its track's spin)."""
    P, C = np.asarray(P, float).reshape(-1, 3), np.asarray(C, float).reshape(-1, 3)
    if len(P) < cfg.min_points:
        return None
    rng = np.random.default_rng(cfg.seed)
    P, C = _at_most(P, C, cfg.max_points, rng)
    sub = rng.choice(len(P), min(cfg.coarse_points, len(P)), replace=False)
    Ps, Cs = P[sub], C[sub]
    centre = np.median(P, 0)  # a few detections bring far background: the mean can be metres off
    starts = [Rigid3(R, centre - R @ a) for R in _distinct(T_fused.R @ _cube_rotations(), symmetry)
              for a in _anchors(geom, cfg.anchors)]
    fused, *coarse = icp_world(geom, [T_fused, *starts], Ps, Cs, cfg.coarse_iters, cfg.huber_m)
    order = np.argsort([depth_fit(geom, T, Ps) for T in coarse], kind="stable")
    picked = [coarse[k] for k in order[:cfg.keep]]
    n_starts = len(starts) + 1
    if cfg.hops:  # kept apart: the hops of one basin would crowd the other basins out of the best few
        axes = np.linalg.svd(geom.samples - geom.samples.mean(0), full_matrices=False)[2]
        hops = [Rigid3(T.R, T.t + T.R @ (sign * h * geom.diameter_m * a)) for T in (fused, *picked) for a in axes
                for sign in (1.0, -1.0) for h in cfg.hops]
        hopped = icp_world(geom, hops, Ps, Cs, cfg.coarse_iters, cfg.huber_m)
        picked += [hopped[k] for k in np.argsort([depth_fit(geom, T, Ps) for T in hopped], kind="stable")[:cfg.keep]]
        n_starts += len(hopped)
    fine = icp_world(geom, [T_fused, *picked], P, C, cfg.iters, cfg.huber_m)
    fits = [depth_fit(geom, T, P) for T in fine]
    best = min(fits)
    near = [i for i, f in enumerate(fits) if f <= best * (1.0 + cfg.tie_rel)]
    if views and scoring is not None and cfg.view_pick_rel > 0 and best <= cfg.view_pick_max_fit * geom.diameter_m:
        wide = [i for i, f in enumerate(fits) if f <= best * (1.0 + cfg.view_pick_rel)]
        seen = {i: view_score(geom, fine[i], views, scoring) for i in wide}
        least = min(seen.values())
        ties = [i for i in wide if seen[i] <= least + cfg.turn_min_px * len(views)]
        best_seen = min(fits[i] for i in ties)  # the best points' fit among the views' ties
        near = [i for i in ties if fits[i] <= best_seen * (1.0 + cfg.tie_rel)]
    pick_i = min(near, key=lambda i: (rotation_error_deg(fine[i].R, T_fused.R, symmetry), i))
    T = canonicalize(fine[pick_i], symmetry, T_fused.R)
    return RefitResult(T, fits[pick_i], fits[0], n_starts)

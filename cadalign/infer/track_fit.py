"""Multi-frame refit of a static part's world pose: one ICP of the CAD to the masked depth of all its detections.

Per frame, a part seen from 7-15 m shows a few dozen depth points: a thin cylinder (a hot stab) fits anywhere along
its axis and either end first, and a small valve's handle fits a quarter turn off. The robust mean of such per-frame
fits keeps their common mistake. The same part seen from the whole orbit, its points moved to the world frame by
the frames' camera poses, fixes all of it. So after the video, a track's world pose is fitted again to the union of
its detections' masked depth points, by point-to-plane ICP in the world frame (a point's facing test uses its own
camera's centre), from its fused pose and from a grid of starts: the fused rotation turned by each of the 24
rotations of the cube, each with a few model points (the centroid and farthest-point samples) put on the points'
centroid. All starts run a few ICP iterations on a subsample; the best few and the fused start run to convergence
on all points. The best fit (mean data -> model distance, each capped at a tenth of the diameter) wins; fits within
``tie_rel`` of it are ties, and of those the one that turns least from the fused pose (symmetry-aware) wins.

Two tracks on one part (a detection given another model of the class starts a second track) are found the same way:
one's refitted pose explains the other's points (:func:`duplicates`).
"""

from __future__ import annotations

import functools
import itertools
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from cadalign.cad.symmetry import Symmetry
from cadalign.config import bounded
from cadalign.eval.pose_metrics import rotation_error_deg
from cadalign.geometry.rotations import axis_angle_to_matrix, orthonormalize
from cadalign.infer.depth_icp import depth_fit
from cadalign.infer.model_geom import ModelGeometry
from cadalign.infer.pose_math import canonicalize
from cadalign.infer.refine_math import clamp_step, huber_weights
from cadalign.types import Rigid3


@dataclass(frozen=True)
class RefitConfig:
    enabled: bool = True
    """Refit each completed track's world pose to all its frames' depth before completion (see module doc)."""
    points_per_frame: int = bounded(300, ge=6)
    """Masked depth points kept per detection (world frame)."""
    max_points: int = bounded(2000, ge=6)
    """Points of the final ICP (a random subset of the union)."""
    coarse_points: int = bounded(300, ge=6)
    """Points of the first, short ICP from every start."""
    coarse_iters: int = bounded(20, ge=1)
    """ICP iterations from every start."""
    keep: int = bounded(4, ge=1)
    """Starts (besides the fused pose) taken on to the final ICP."""
    iters: int = bounded(30, ge=1)
    """Final ICP iterations."""
    anchors: int = bounded(12, ge=1)
    """Model points put on the points' centroid per start rotation (its centroid, then farthest-point samples)."""
    tie_rel: float = bounded(0.02, ge=0)
    """Fits within this fraction of the best are ties (the one nearest the fused pose wins)."""
    huber_m: float = bounded(0.005, gt=0)
    """Huber threshold of the point-to-plane residuals, metres."""
    min_points: int = bounded(30, ge=6)
    """A track with fewer points in all keeps its fused pose."""
    ego: bool = False
    """Refit tracks in the worlds of camera poses registered on the parts (temporal mode ``ego``) too. Off: those
    poses carry the registration's errors into the union of points. Default orbit, 33 held-out frames, true depth,
    ``accurate`` with ``temporal.mode = "ego"``, valve / hot stab F1 and fused R mean, without -> with: seed 0
    0.896 / 0.562, 3.55 / 30.5 deg -> 0.917 / 0.523, 5.09 / 7.7 deg; seed 1 0.877 / 0.483, 3.22 / 15.7 deg ->
    0.890 / 0.511, 5.72 / 55.6 deg."""
    dup_tol: float = bounded(0.02, gt=0)
    """A point is explained by a pose when within this fraction of the diameter of the model (the duplicate test)."""
    dup_share: float = bounded(0.8, ge=0, le=1)
    """Two refitted tracks of a class are one part (a second track, often with the wrong model of the class, e.g.
    the UUV hot stab fitted onto a procedural one's probe, or a retired track and its successor) when one's pose
    explains at least this share of what the other's own pose explains of the other's points; the one explaining
    more of both tracks' points is kept, and the other's records are dropped when the kept one is completed
    (:func:`duplicates`). 0 = off."""
    seed: int = 0
    """Seed of the point subsampling."""


@dataclass(frozen=True)
class RefitResult:
    """The refitted pose, its fit and the fused pose's fit after its own ICP (mean capped distance, m)."""

    T_world_from_obj: Rigid3
    fit_m: float
    fused_fit_m: float
    starts: int


@dataclass
class TrackPoints:
    """Masked depth points per track, in the world frame, with the centre of the camera that saw each."""

    cfg: RefitConfig
    _points: dict = field(default_factory=lambda: defaultdict(list))
    _rng: np.random.Generator = field(init=False)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.cfg.seed)

    def add(self, track_id: int, Q_cam: np.ndarray, T_world_from_cam: Rigid3) -> None:
        """Keep up to ``points_per_frame`` of one detection's camera-frame points ``Q_cam`` (N, 3)."""
        Q = np.asarray(Q_cam, float).reshape(-1, 3)
        if len(Q) > self.cfg.points_per_frame:
            Q = Q[np.sort(self._rng.choice(len(Q), self.cfg.points_per_frame, replace=False))]
        if len(Q):
            self._points[track_id].append((T_world_from_cam.apply(Q), T_world_from_cam.t))

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
    return float(np.mean(geom.tree.query(T.inverse().apply(P), distance_upper_bound=tol_m)[0] <= tol_m))


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


def duplicates(tracks: Sequence[FittedTrack], cfg: RefitConfig) -> dict[int, int]:
    """``{track id: the track id it duplicates}`` (``cfg.dup_share``).

    Two tracks of one class and world, their models within reach of each other, are one part when one's pose
    explains the other's points at least ``dup_share`` times as well as the other's own pose does (points within
    ``dup_tol`` of the smaller model's diameter). Of the two, the one whose pose explains more of both tracks' points
    is kept (ties: more detections, then the lower id). Tracks are visited by detections, most first."""
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
            if explained(a.geom, a.T_world_from_obj, both, tol) > explained(b.geom, b.T_world_from_obj, both, tol):
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
                     symmetry: Symmetry | None = None) -> RefitResult | None:
    """The world pose of a static part fitted to all its points ``P`` (N, 3) seen from ``C`` (N, 3), searched from
    ``T_fused`` and a grid of starts (module doc); None with fewer than ``cfg.min_points`` points.

    The result is the symmetric equivalent nearest ``T_fused`` (a spun cylinder keeps its track's spin)."""
    P, C = np.asarray(P, float).reshape(-1, 3), np.asarray(C, float).reshape(-1, 3)
    if len(P) < cfg.min_points:
        return None
    rng = np.random.default_rng(cfg.seed)
    if len(P) > cfg.max_points:
        pick = rng.choice(len(P), cfg.max_points, replace=False)
        P, C = P[pick], C[pick]
    sub = rng.choice(len(P), min(cfg.coarse_points, len(P)), replace=False)
    Ps, Cs = P[sub], C[sub]
    centre = P.mean(0)
    starts = [Rigid3(R, centre - R @ a) for R in _distinct(T_fused.R @ _cube_rotations(), symmetry)
              for a in _anchors(geom, cfg.anchors)]
    coarse = icp_world(geom, starts, Ps, Cs, cfg.coarse_iters, cfg.huber_m)
    order = np.argsort([depth_fit(geom, T, Ps) for T in coarse], kind="stable")
    fine = icp_world(geom, [T_fused, *(coarse[k] for k in order[:cfg.keep])], P, C, cfg.iters, cfg.huber_m)
    fits = [depth_fit(geom, T, P) for T in fine]
    best = min(fits)
    near = [i for i, f in enumerate(fits) if f <= best * (1.0 + cfg.tie_rel)]
    pick_i = min(near, key=lambda i: (rotation_error_deg(fine[i].R, T_fused.R, symmetry), i))
    T = canonicalize(fine[pick_i], symmetry, T_fused.R)
    return RefitResult(T, fits[pick_i], fits[0], len(starts) + 1)

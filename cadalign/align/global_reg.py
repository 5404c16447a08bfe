"""Global (prior-free) CAD <-> SfM registration with unknown scale: FPFH + RANSAC under scale hypotheses.

1. Scale hypotheses. FPFH features are not scale invariant, so the SfM cloud is first brought to roughly
   the CAD's size: both clouds are normalised by a robust radius (median distance to the median point).
   Clutter (seabed, a neighbouring structure) makes the SfM cloud's radius larger or smaller than the
   structure's, so a few relative scale hypotheses are tried around that ratio.
2. Features and RANSAC. Both clouds are voxel-downsampled at a fraction of the CAD diameter; FPFH
   features are matched mutually (flat regions such as the seabed all share one feature, and mutual
   matching drops most of those ambiguous pairs); RANSAC fits a rigid transform (its edge check tolerates
   the remaining scale error) and a similarity refit on its inliers corrects part of the scale.
3. Short Sim(3) ICP and scoring. Each estimate is refined by a short guarded Sim(3) ICP and scored.
4. Symmetric turns. Man-made structures are nearly symmetric, and features cannot tell the halves apart:
   the best candidates are turned by the 24 rotations that map the CAD's box axes onto themselves, the
   turns are screened cheaply, and the best few refined and scored, until the best candidates have all
   been turned.

The score is the F-score of precision (fraction of SfM points near the CAD) and coverage (fraction of the
CAD near SfM points): precision alone prefers a shrunken cloud, coverage alone an inflated one.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass, replace

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from cadalign.align.config import GlobalRegConfig, Sim3ICPConfig
from cadalign.align.icp import sim3_icp, subsample
from cadalign.align.surface import CadSurface, query_workers
from cadalign.errors import AlignmentError, DegenerateGeometryError
from cadalign.geometry import umeyama
from cadalign.types import Sim3

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Candidate:
    """A scored coarse estimate of ``cad_from_sfm``.

    Attributes:
        cad_from_sfm: the estimate after a short Sim(3) ICP.
        score: F-score of precision and coverage (higher is better), in [0, 1].
        precision: fraction of SfM points within the score distance of the CAD.
        coverage: fraction of CAD samples within the score distance of an SfM point.
        scale_factor: the scale hypothesis it came from (relative to the robust size ratio).
        turn: index into :func:`axis_turns` of the last turn applied (0: none).
    """

    cad_from_sfm: Sim3
    score: float
    precision: float
    coverage: float
    scale_factor: float
    turn: int


def robust_centre_radius(points: np.ndarray) -> tuple[np.ndarray, float]:
    """The median point (3,) and the median distance to it: a size measure robust to outliers."""
    c = np.median(points, axis=0)
    return c, float(np.median(np.linalg.norm(points - c, axis=1)))


def _pcd(points: np.ndarray, voxel: float, normal_radius: float):  # -> open3d PointCloud
    import open3d as o3d  # lazy: heavy dependency (open3d)

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(normal_radius, 30))
    return pcd


def _fpfh(pcd, radius: float):  # -> open3d Feature
    import open3d as o3d  # lazy: heavy dependency (open3d)

    return o3d.pipelines.registration.compute_fpfh_feature(pcd, o3d.geometry.KDTreeSearchParamHybrid(radius, 100))


def _correspondences(f_src: np.ndarray, f_dst: np.ndarray, min_count: int = 50) -> np.ndarray:
    """(K, 2) index pairs of mutual nearest neighbours in FPFH space (features (N, 33) and (M, 33)).

    Mutual matching drops most of the ambiguous matches from flat regions (seabed, large faces), which
    all share one feature; when it leaves fewer than ``min_count`` pairs, the plain nearest neighbours of
    the most distinctive source points (Lowe ratio) are added.
    """

    d, j = cKDTree(f_dst).query(f_src, k=2, workers=-1)
    back = cKDTree(f_src).query(f_dst, workers=-1)[1]
    i = np.arange(len(f_src))
    mutual = back[j[:, 0]] == i
    pairs = np.column_stack([i[mutual], j[mutual, 0]])
    if len(pairs) < min_count:
        ratio = d[:, 0] / np.maximum(d[:, 1], 1e-12)
        extra = np.argsort(ratio)[: min_count]
        extra = extra[~mutual[extra]]
        pairs = np.concatenate([pairs, np.column_stack([extra, j[extra, 0]])])
    return pairs.astype(np.int32)


SCREEN_POINTS = 1500
"""SfM points used to screen the turned variants of a candidate."""

SCREEN_ICP_ITERS = 3
"""ICP iterations (at the widest distance) before a turned variant is screened."""

MAX_INLIER_REFIT_SCALE = 1.5
"""The similarity refit on RANSAC's inliers may change the hypothesis scale by at most this factor."""


def _ransac(src, dst, pairs: np.ndarray, voxel: float, cfg: GlobalRegConfig, seed: int) -> Sim3 | None:
    """One RANSAC run on feature correspondences: ``dst_from_src``, or ``None`` when it found no model.

    RANSAC is rigid on purpose: it scores a model by its fitness, and a similarity that shrinks the source
    to a point near the target has fitness 1, so with a free scale it returns ``s = 0``. The scale error
    left by the hypothesis is then corrected by a similarity (Umeyama) refit on RANSAC's inlier pairs,
    and the short Sim(3) ICP that follows corrects the rest.
    """
    import open3d as o3d  # lazy: heavy dependency (open3d)

    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)
    dist = cfg.ransac_dist_vox * voxel
    res = reg.registration_ransac_based_on_correspondence(
        src, dst, o3d.utility.Vector2iVector(pairs), dist, reg.TransformationEstimationPointToPoint(False), 3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(cfg.edge_similarity),
         reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(cfg.ransac_max_iters, cfg.ransac_confidence),
    )
    corr = np.asarray(res.correspondence_set)
    if len(corr) < 3:
        return None
    M = np.asarray(res.transformation)
    rigid = Sim3(1.0, M[:3, :3], M[:3, 3])
    try:
        refit = umeyama(np.asarray(src.points)[corr[:, 0]], np.asarray(dst.points)[corr[:, 1]], with_scale=True)
    except DegenerateGeometryError:
        return rigid
    return refit if 1 / MAX_INLIER_REFIT_SCALE < refit.s < MAX_INLIER_REFIT_SCALE else rigid


def score_alignment(points_sfm: np.ndarray, surface: CadSurface, T: Sim3, dist_m: float,
                    cad_subset: np.ndarray) -> tuple[float, float, float]:
    """(F-score, precision, coverage) of ``cad_from_sfm = T`` at distance ``dist_m``.

    Args:
        points_sfm: (N, 3) SfM points.
        surface: CAD samples.
        T: ``cad_from_sfm``.
        dist_m: a point (sample) within this distance of the other set counts.
        cad_subset: indices of the CAD samples used for coverage.
    """

    y = T.apply(points_sfm)
    d, _ = surface.tree.query(y, distance_upper_bound=dist_m, workers=query_workers(len(y)))
    precision = float(np.mean(np.isfinite(d)))
    d2, _ = cKDTree(y).query(surface.points_m[cad_subset], distance_upper_bound=dist_m,
                             workers=query_workers(len(cad_subset)))
    coverage = float(np.mean(np.isfinite(d2)))
    f = 0.0 if precision + coverage == 0 else 2 * precision * coverage / (precision + coverage)
    return f, precision, coverage


def _box_frames(surface: CadSurface) -> list[tuple[np.ndarray, np.ndarray]]:
    """(axes (3, 3) as columns, centre (3,)) of the CAD's axis-aligned box and of its minimum-volume box.

    Not principal axes: those are arbitrary within the plane of a square-ish footprint.
    """

    lo, hi = surface.vertices_m.min(axis=0), surface.vertices_m.max(axis=0)
    frames = [(np.eye(3), 0.5 * (lo + hi))]
    try:
        T_box_from_world, _ = trimesh.bounds.oriented_bounds(surface.vertices_m)
    except Exception as exc:  # qhull fails on flat or tiny inputs; the axis-aligned box still works
        log.debug("no oriented bounding box (%s); using the axis-aligned box only", exc)
        return frames
    world_from_box = np.linalg.inv(T_box_from_world)
    frames.append((world_from_box[:3, :3], world_from_box[:3, 3]))
    return frames


def axis_turns(surface: CadSurface) -> list[Sim3]:
    """The rotations mapping the CAD's box axes onto themselves (up to sign), about the box centre.

    24 per box (the CAD frame's axis-aligned box and the minimum-volume box; duplicates dropped). A
    box-like structure is nearly invariant under some of them (180 degrees about any axis; 90 degrees
    about an axis whose two cross extents are similar), so a feature match can land on the wrong one.
    Frames and skids are symmetric about their box centre, while their area centroid is pulled towards
    whatever asymmetric equipment sits inside. The identity comes first.
    """

    out: list[Sim3] = []
    seen: set[tuple[float, ...]] = set()
    for B, c in _box_frames(surface):
        for perm in itertools.permutations(range(3)):
            for signs in itertools.product((1.0, -1.0), repeat=3):
                P = np.zeros((3, 3))
                P[np.arange(3), perm] = signs
                if np.linalg.det(P) < 0:
                    continue
                R = B @ P @ B.T
                key = tuple(np.round(R, 4).ravel())
                if key not in seen:
                    seen.add(key)
                    out.append(Sim3(1.0, R, c - R @ c))
    out.sort(key=lambda G: -np.trace(G.R))
    return out


def ransac_candidates(points_sfm: np.ndarray, surface: CadSurface, cfg: GlobalRegConfig, seed: int) -> list[
        tuple[float, Sim3]]:
    """Raw RANSAC estimates of ``cad_from_sfm``, one per scale hypothesis and seed: ``(factor, T)`` pairs."""
    c_sfm, r_sfm = robust_centre_radius(points_sfm)
    c_cad, r_cad = robust_centre_radius(surface.points_m)
    if not r_sfm > 0:
        raise AlignmentError("the SfM points are (almost) all identical; check the SfM reconstruction")
    voxel = cfg.voxel_rel * surface.diameter_m
    dst = _pcd(surface.points_m - c_cad, voxel, cfg.normal_radius_vox * voxel)
    f_dst = np.asarray(_fpfh(dst, cfg.feature_radius_vox * voxel).data).T
    s_base = r_cad / r_sfm
    out = []
    for factor in cfg.scale_factors:
        s = s_base * factor
        src = _pcd(s * (points_sfm - c_sfm), voxel, cfg.normal_radius_vox * voxel)
        if len(src.points) < 10:
            continue
        pairs = _correspondences(np.asarray(_fpfh(src, cfg.feature_radius_vox * voxel).data).T, f_dst)
        for k in range(cfg.candidates_per_hypothesis):
            M = _ransac(src, dst, pairs, voxel, cfg, seed + 7919 * k)
            if M is None:
                continue
            T = Sim3(1.0, np.eye(3), c_cad) @ M @ Sim3(s, np.eye(3), -s * c_sfm)
            out.append((factor, T))
    return out


@dataclass(frozen=True, eq=False)
class _Scorer:
    """Short guarded Sim(3) ICP, scoring, and the turned variants of a candidate."""

    pts: np.ndarray
    surface: CadSurface
    icp: Sim3ICPConfig
    iters: int
    dist_m: float
    cad_subset: np.ndarray
    turns: list[Sim3]
    n_refined: int

    def refine(self, T: Sim3) -> Sim3:
        return sim3_icp(self.pts, self.surface, T, self.icp, iters_per_level=self.iters)[0]

    def candidate(self, T: Sim3, factor: float, turn: int) -> Candidate:
        f, p, c = score_alignment(self.pts, self.surface, T, self.dist_m, self.cad_subset)
        log.debug("candidate factor %.2f turn %d: score %.3f (precision %.3f, coverage %.3f), s %.4g",
                  factor, turn, f, p, c, T.s)
        return Candidate(T, f, p, c, factor, turn)

    def screen(self, T: Sim3) -> float:
        """A cheap score: a few ICP iterations at the widest distance on a small subset, then a loose F-score.

        The few iterations matter: a turned candidate inherits the scale and offset errors of its source,
        and without them the right turn can score below wrong ones.
        """
        pts = self.pts[:: max(1, len(self.pts) // SCREEN_POINTS)]
        widest = [self.icp.corr_dist_schedule_rel[0] * self.surface.diameter_m]
        T, _ = sim3_icp(pts, self.surface, T, self.icp, schedule_m=widest, iters_per_level=SCREEN_ICP_ITERS)
        return score_alignment(pts, self.surface, T, 2 * self.dist_m, self.cad_subset[:5000])[0]

    def variants(self, T1: Sim3, factor: float, *, skip_identity: bool = False) -> list[Candidate]:
        """Screen the turns of ``T1`` cheaply, then refine and score the best few."""
        scores = [(self.screen(G @ T1), k) for k, G in enumerate(self.turns) if not (skip_identity and k == 0)]
        best = sorted(scores, reverse=True)[: self.n_refined]
        return [self.candidate(T1 if k == 0 else self.refine(self.turns[k] @ T1), factor, k) for _, k in best]


def global_registration(
    points_sfm: np.ndarray, surface: CadSurface, cfg: GlobalRegConfig, icp_cfg: Sim3ICPConfig, seed: int
) -> list[Candidate]:
    """Scored coarse estimates of ``cad_from_sfm``, best first (see the module docstring).

    Each RANSAC estimate is refined by a short ICP and scored; then the turned variants of the best few
    candidates are screened, refined and scored, until the best few have all been turned.

    Args:
        points_sfm: (N, 3) SfM points.
        surface: CAD samples (metres).
        cfg: global registration knobs.
        icp_cfg: the Sim(3) ICP knobs (the short refinement uses ``cfg.score_schedule_rel``).
        seed: seed of the subsets and RANSAC.

    Raises:
        AlignmentError: no candidate at all (too few points after downsampling, or RANSAC failed).
    """
    raw = ransac_candidates(points_sfm, surface, cfg, seed)
    pts = subsample(points_sfm, cfg.max_points, seed)
    if not raw:
        raise AlignmentError(
            f"global registration found no candidate for {len(points_sfm)} SfM points: the cloud is too sparse "
            f"at voxel {cfg.voxel_rel:g} x CAD diameter; lower global_reg.voxel_rel, or give picks or a prior pose"
        )
    rng = np.random.default_rng(seed)
    # a short ICP only has to reach the right basin: a looser convergence test saves most of its time
    short = replace(icp_cfg, corr_dist_schedule_rel=cfg.score_schedule_rel, tol_rel=max(icp_cfg.tol_rel, 1e-4))
    scorer = _Scorer(
        pts, surface, short, cfg.score_icp_iters, cfg.score_dist_rel * surface.diameter_m,
        rng.choice(len(surface.points_m), min(len(surface.points_m), 20_000), replace=False),
        axis_turns(surface) if cfg.symmetry_variants else [Sim3()], cfg.variants_refined,
    )
    out = [scorer.candidate(scorer.refine(T0), factor, 0) for factor, T0 in raw]
    if cfg.symmetry_variants:
        out.sort(key=lambda c: -c.score)
        polished: set[int] = set()
        for _ in range(cfg.polish_rounds):
            todo = [c for c in out[: cfg.variants_of_top] if id(c) not in polished]
            if not todo:
                break
            for c in todo:
                polished.add(id(c))
                out += scorer.variants(c.cad_from_sfm, c.scale_factor, skip_identity=True)
            out.sort(key=lambda c: -c.score)
    out.sort(key=lambda c: -c.score)
    return out

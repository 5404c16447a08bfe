"""The in-memory alignment: coarse estimate, Sim(3) ICP, point-to-plane refinement, quality gates."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from cadalign.align.config import AlignConfig
from cadalign.align.gates import check_gates, format_report, gate_distances, measure, raise_if_failed
from cadalign.align.global_reg import Candidate, global_registration
from cadalign.align.icp import refine_point_to_plane, sim3_icp, subsample
from cadalign.align.picks import Picks, sim3_from_picks
from cadalign.align.result import AlignResult, IcpStep
from cadalign.align.surface import CadPart, CadSurface, query_workers, sample_surface
from cadalign.errors import InputError
from cadalign.geometry import geodesic_angle
from cadalign.types import Sim3

log = logging.getLogger(__name__)

MIN_POINTS = 10
"""Fewest finite SfM points accepted at all (the gates ask for many more inliers)."""

DISTINCT_DEG = 5.0
"""Candidates whose rotations differ by more than this (degrees) are different poses, not the same one."""

AMBIGUITY_WARN = 0.985
"""A final pose turned more than :data:`DISTINCT_DEG` away scoring above this fraction of the best is
warned about: the structure is nearly symmetric for this cloud and the global result may be the wrong one."""


def check_points(points: object, name: str = "points_sfm") -> np.ndarray:
    """``points`` as a float64 (N, 3) array with non-finite rows dropped (logged).

    Raises:
        InputError: wrong shape, or fewer than :data:`MIN_POINTS` finite points.
    """
    return _finite_points(points, name)[0]


def _finite_points(points: object, name: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`check_points`, and which rows of ``points`` it kept (N,) bool."""
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise InputError(f"{name} must have shape (N, 3), got {arr.shape}")
    finite = np.all(np.isfinite(arr), axis=1)
    if not finite.all():
        log.warning("%s: dropped %d non-finite points of %d", name, int((~finite).sum()), len(arr))
        arr = arr[finite]
    if len(arr) < MIN_POINTS:
        raise InputError(f"{name} has {len(arr)} finite points; the alignment needs at least {MIN_POINTS} "
                         "(many more in practice): check the SfM reconstruction")
    return arr, finite


def _coarse_method(cfg: AlignConfig, picks: Picks | None, prior: Sim3 | None) -> str:
    method = cfg.coarse
    if method == "auto":
        method = "picks" if picks is not None else "prior" if prior is not None else "global"
    if method == "picks" and picks is None:
        raise InputError("coarse = 'picks' needs point correspondences; pass a picks file (see cadalign.align.picks)")
    if method == "prior" and prior is None:
        raise InputError("coarse = 'prior' needs a prior cad_from_sfm pose; pass one or use coarse = 'global'")
    return method


def distinct_candidates(cands: list[Candidate], k: int, min_deg: float = DISTINCT_DEG) -> list[Candidate]:
    """The best ``k`` candidates whose rotations differ pairwise by more than ``min_deg`` degrees."""
    out: list[Candidate] = []
    for c in cands:
        if all(np.degrees(geodesic_angle(c.cad_from_sfm.R, o.cad_from_sfm.R)) > min_deg for o in out):
            out.append(c)
            if len(out) == k:
                break
    return out


def _starts(points: np.ndarray, surface: CadSurface, cfg: AlignConfig, method: str, picks: Picks | None,
            prior: Sim3 | None) -> tuple[list[Sim3], list[Sim3]]:
    """The coarse estimates to refine (one for picks or a prior, the best distinct ones for global), and the
    next distinct global candidates kept unrefined as hypotheses for the image verification."""
    if method == "picks":
        assert picks is not None
        return [sim3_from_picks(picks)], []
    if method == "prior":
        assert prior is not None
        return [prior], []
    cands = global_registration(points, surface, cfg.global_reg, cfg.icp, cfg.seed)
    n = cfg.global_reg.final_candidates
    distinct = [c.cad_from_sfm for c in distinct_candidates(cands, max(n, cfg.global_reg.hypotheses))]
    return distinct[:n], distinct[n:]



def final_score(points: np.ndarray, surface: CadSurface, T: Sim3, inlier_m: float, seed: int) -> float:
    """F-score of precision (points within ``inlier_m`` of the CAD surface, exact distances) and coverage
    (CAD samples within ``inlier_m`` of an aligned point), on seeded subsets of at most 20k each."""
    pts = subsample(points, 20_000, seed)
    y = T.apply(pts)
    inl = surface.distances(y) <= inlier_m
    if not inl.any():
        return 0.0
    cad = subsample(surface.points_m, 20_000, seed)
    d, _ = cKDTree(y[inl]).query(cad, distance_upper_bound=inlier_m, workers=query_workers(len(cad)))
    precision, coverage = float(inl.mean()), float(np.isfinite(d).mean())
    return 2 * precision * coverage / (precision + coverage) if precision + coverage > 0 else 0.0


def _refine(points: np.ndarray, surface: CadSurface, start: Sim3, cfg: AlignConfig,
            seconds: dict[str, float]) -> tuple[Sim3, list[IcpStep]]:
    """Sim(3) ICP then point-to-plane refinement from ``start``; adds their wall times to ``seconds``."""
    t0 = time.perf_counter()
    T, history = sim3_icp(points, surface, start, cfg.icp)
    t1 = time.perf_counter()
    if cfg.refine.enabled:
        T, step = refine_point_to_plane(points, surface, T, cfg.refine)
        history += [step] if step is not None else []
    seconds["sim3_icp"] = seconds.get("sim3_icp", 0.0) + t1 - t0
    seconds["refine"] = seconds.get("refine", 0.0) + time.perf_counter() - t1
    return T, history


def align(
    points_sfm: np.ndarray,
    cad: CadSurface | Sequence[CadPart],
    cfg: AlignConfig | None = None,
    *,
    picks: Picks | None = None,
    prior: Sim3 | None = None,
    context: str = "the SfM cloud",
    views: np.ndarray | None = None,
) -> AlignResult:
    """Estimate ``cad_from_sfm`` (SfM coordinates -> CAD/world metres) and check its quality.

    Coarse estimate (global FPFH+RANSAC over scale hypotheses, user picks, or a prior pose), then Sim(3)
    ICP with a scale guard, then rigid robust point-to-plane refinement, then the quality gates. The
    global path refines its best few distinct candidates this way and keeps the best final fit, so
    near-symmetric look-alikes are compared at full resolution.

    Args:
        points_sfm: (N, 3) SfM points in the SfM frame (any unit); non-finite rows are dropped.
        cad: CAD surface samples, or the structure's parts (models in metres with their world poses).
        cfg: configuration (default: the ``balanced`` preset).
        picks: point correspondences for ``coarse = picks`` (or ``auto``).
        prior: a prior ``cad_from_sfm`` for ``coarse = prior`` (or ``auto``).
        context: how messages name the input (e.g. its path).
        views: (N,) the number of images each point is seen in, if known (the fitness gate counts the
            multi-view points, :attr:`~cadalign.align.config.GateConfig.fitness_min_views`).

    Returns:
        The gated :class:`AlignResult`.

    Raises:
        AlignmentGateError: (an :class:`~cadalign.errors.AlignmentError`) a quality gate failed; the
            message lists every gate with its numbers and the likely causes.
        InputError: unusable points or CAD, or a coarse method without its input.
        DegenerateGeometryError: degenerate picks.
    """
    cfg = cfg or AlignConfig()
    t0 = time.perf_counter()
    points, kept = _finite_points(points_sfm, "points_sfm")
    views = None if views is None else np.asarray(views)[kept]
    method = _coarse_method(cfg, picks, prior)
    surface = cad if isinstance(cad, CadSurface) else sample_surface(cad, cfg.cad_samples, cfg.seed)
    t1 = time.perf_counter()
    starts, extras = _starts(points, surface, cfg, method, picks, prior)
    seconds = {"sample": t1 - t0, "coarse": time.perf_counter() - t1}
    icp_points = subsample(points, cfg.icp.max_points, cfg.seed)
    inlier_m = gate_distances(surface, cfg.gates)[0]
    finals = []
    for start in starts:
        T, history = _refine(icp_points, surface, start, cfg, seconds)
        finals.append((final_score(points, surface, T, inlier_m, cfg.seed), T, history, start))
    finals.sort(key=lambda f: -f[0])
    score, T, history, coarse = finals[0]
    scores = None if method != "global" else (score, finals[1][0] if len(finals) > 1 else 0.0)
    # the warning is for the log; the symmetry-margin gate decides
    if scores is not None and scores[1] > AMBIGUITY_WARN * scores[0]:
        log.warning("global registration is ambiguous: a pose turned > %g deg away fits almost as well "
                    "(%.3f vs %.3f); the structure looks nearly symmetric from this cloud, check align.png or "
                    "give picks", DISTINCT_DEG, scores[1], scores[0])
    t4 = time.perf_counter()
    metrics = measure(points, surface, T, cfg.gates, views)
    checks = check_gates(metrics, T, coarse, surface, cfg.gates, scores)
    seconds["gates"] = time.perf_counter() - t4
    raise_if_failed(checks, metrics, T, context)
    log.info("%s", format_report(checks, metrics, T, context))
    # the refined ones first (the result is the first), then the unrefined global candidates
    hypotheses = tuple((f[1], f[0]) for f in finals) + tuple(
        (E, final_score(points, surface, E, inlier_m, cfg.seed)) for E in extras
        if all(np.degrees(geodesic_angle(E.R, f[1].R)) > DISTINCT_DEG for f in finals))
    return AlignResult(T, method, coarse, metrics, checks, seconds, tuple(history), scores, hypotheses)

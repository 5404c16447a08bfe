"""Quality gates of an alignment: residual metrics, checks against thresholds, and a readable report.

A bad alignment is never returned as a success: :func:`check_gates` lists every gate with its value and
threshold, and :func:`raise_if_failed` raises :class:`AlignmentGateError` whose message carries the
numbers and the likely causes (a CAD in the wrong unit, the wrong CAD, too few points on the structure).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from cadalign.align.config import GateConfig
from cadalign.align.result import AlignMetrics, GateCheck
from cadalign.align.surface import CadSurface, query_workers
from cadalign.errors import AlignmentError
from cadalign.types import Sim3

UNIT_HINT = ("check the CAD unit: a CAD in millimetres read as metres makes everything 1000x too big (an "
             "inch file 25.4x, cm 10x), and one in metres read as millimetres 1000x too small; pass the "
             "unit to load_cad(path, unit=...)")


class AlignmentGateError(AlignmentError):
    """An alignment failed one or more quality gates.

    Attributes:
        checks: every gate, passed or not.
        metrics: the residual statistics.
        cad_from_sfm: the rejected estimate (for debugging only; do not use it).
    """

    def __init__(self, message: str, checks: tuple[GateCheck, ...], metrics: AlignMetrics, cad_from_sfm: Sim3):
        super().__init__(message)
        self.checks = checks
        self.metrics = metrics
        self.cad_from_sfm = cad_from_sfm

    @property
    def failed(self) -> tuple[str, ...]:
        """Names of the failed gates."""
        return tuple(c.name for c in self.checks if not c.passed)


def residuals_m(points_sfm: np.ndarray, surface: CadSurface, cad_from_sfm: Sim3) -> np.ndarray:
    """(N,) distance of each aligned SfM point to the CAD surface samples, metres."""
    return surface.distances(cad_from_sfm.apply(points_sfm))


def gate_distances(surface: CadSurface, cfg: GateConfig) -> tuple[float, float]:
    """The effective ``(inlier, roi)`` distances in metres: the metric values capped relative to the CAD."""
    return (min(cfg.inlier_dist_m, cfg.inlier_dist_rel * surface.diameter_m),
            min(cfg.roi_dist_m, cfg.roi_dist_rel * surface.diameter_m))


def measure(points_sfm: np.ndarray, surface: CadSurface, cad_from_sfm: Sim3, cfg: GateConfig,
            views: np.ndarray | None = None) -> AlignMetrics:
    """Residual statistics of ``cad_from_sfm`` (see :class:`AlignMetrics` and :class:`GateConfig`); ``views``
    (N,) the number of images each point is seen in, when known (the fitness counts the multi-view ones)."""
    inlier_m, roi_m = gate_distances(surface, cfg)
    y = cad_from_sfm.apply(points_sfm)
    d = surface.distances(y)
    inl = d <= inlier_m
    lo, hi = surface.points_m.min(axis=0) + roi_m, surface.points_m.max(axis=0) - roi_m
    roi = (d <= roi_m) | np.all((y > lo) & (y < hi), axis=1)
    n_inl, n_roi = int(inl.sum()), int(roi.sum())
    counted = roi if views is None else roi & (np.asarray(views) >= cfg.fitness_min_views)
    if counted.sum() < cfg.min_inliers:  # too few multi-view points to judge by: all count
        counted = roi
    n_fit = int(counted.sum())
    if n_inl:
        cov_d, _ = cKDTree(y[inl]).query(surface.points_m, distance_upper_bound=inlier_m,
                                         workers=query_workers(len(surface.points_m)))
        coverage = float(np.mean(np.isfinite(cov_d)))
    else:
        coverage = 0.0
    return AlignMetrics(
        fitness=int((inl & counted).sum()) / n_fit if n_fit else 0.0,
        inlier_rmse_m=float(np.sqrt(np.mean(d[inl] ** 2))) if n_inl else float("inf"),
        n_inliers=n_inl,
        n_roi=n_roi,
        n_points=len(points_sfm),
        coverage=coverage,
        median_residual_m=float(np.median(d[roi])) if n_roi else float("inf"),
        n_fitness=n_fit,
    )


def _check(name: str, value: float, op: str, threshold: float | tuple[float, float], hint: str) -> GateCheck:
    if op == ">=":
        ok = value >= threshold
    elif op == "<=":
        ok = value <= threshold
    else:
        lo, hi = threshold
        ok = lo <= value <= hi
    return GateCheck(name, float(value), threshold, op, bool(ok and np.isfinite(value)), hint)


def check_gates(
    metrics: AlignMetrics,
    cad_from_sfm: Sim3,
    coarse: Sim3,
    surface: CadSurface,
    cfg: GateConfig,
    global_scores: tuple[float, float] | None = None,
) -> tuple[GateCheck, ...]:
    """Every quality gate of an alignment, in the order they are reported.

    ``global_scores`` (best, runner-up) final fit scores of a global registration enable the symmetry
    margin gate; picks and prior poses skip it (the user decided).
    """
    ratio = cad_from_sfm.s / coarse.s
    checks = [
        _check("cad_extent_m", surface.extent_m, "in", tuple(cfg.cad_size_range_m),
               f"the whole CAD structure is {surface.extent_m:.4g} m across, implausible for subsea hardware; "
               + UNIT_HINT),
        _check("fitness", metrics.fitness, ">=", cfg.min_fitness,
               "the points near the CAD do not lie on its surface: the wrong CAD (or a different revision of "
               "the structure), a wrong coarse alignment (a near-symmetric structure can be matched turned "
               "around; give picks), or a wrong scale (" + UNIT_HINT + ")"),
        _check("inlier_rmse_m", metrics.inlier_rmse_m, "<=", cfg.max_rmse_m,
               "the residuals are larger than underwater SfM noise: a metric scale that is too large (" + UNIT_HINT
               + "), a poor SfM reconstruction, or the wrong CAD"),
        _check("inlier_rmse_floor_m", metrics.inlier_rmse_m, ">=", cfg.min_rmse_m,
               "the residuals are implausibly small for underwater SfM, so the metric scale is far too small ("
               + UNIT_HINT + ")"),
        _check("n_inliers", metrics.n_inliers, ">=", cfg.min_inliers,
               "too few SfM points lie on the CAD: the video sees too little of the structure, the SfM is too "
               "sparse, or the CAD/scale is wrong"),
        _check("inlier_fraction_all", metrics.n_inliers / max(metrics.n_points, 1), ">=", cfg.min_inlier_frac_all,
               "too few of all SfM points are on the structure (mostly seabed or other clutter): crop the "
               "cloud to the structure or survey it more closely"),
        _check("scale_change_vs_coarse", ratio, "in", (1 / cfg.max_scale_change, cfg.max_scale_change),
               "ICP moved the scale far from the coarse estimate (it ran into the scale guard): clutter with no "
               "CAD counterpart, or a poor coarse alignment; give picks or a prior pose"),
    ]
    if global_scores is not None:
        best, runner = global_scores
        checks.append(_check(
            "symmetry_margin", (best - runner) / best if best > 0 else 0.0, ">=", cfg.min_symmetry_margin,
            "a pose turned by more than 5 degrees fits almost as well: the structure is nearly symmetric as seen "
            "by this cloud and the global registration cannot tell which way round it is; give 3+ picks on "
            "asymmetric features (see cadalign.align.picks) or a prior pose"))
    if cfg.expected_scale is not None:
        checks.append(_check(
            "scale_vs_expected", cad_from_sfm.s / cfg.expected_scale, "in",
            (1 / cfg.expected_scale_tol, cfg.expected_scale_tol),
            "the scale disagrees with the expected scale from navigation: " + UNIT_HINT))
    return tuple(checks)


SCALE_GATES = ("cad_extent_m", "inlier_rmse_m", "inlier_rmse_floor_m", "scale_vs_expected")
"""Gates whose failure points at the CAD's unit first."""

SHORT_COVERAGE = 0.35
"""A cloud explaining less of the CAD than this (coverage) comes from a capture that saw little of it."""

SHORT_POINTS = 3000
"""Fewer SfM points than this is a short or low-resolution clip (the README gives the smallest capture)."""


def likely_causes(failed: list[GateCheck], metrics: AlignMetrics) -> list[str]:
    """The likely causes of the failed gates, most likely first.

    A unit mix-up comes first only when a scale gate failed; a capture that saw little of the structure
    (few points, low coverage) comes first otherwise, and the gates' own hints name the unit only in passing."""
    if not failed:
        return []
    names = {c.name for c in failed}
    scale = bool(names & set(SCALE_GATES))
    causes = [UNIT_HINT] if scale else []
    if metrics.coverage < SHORT_COVERAGE or metrics.n_points < SHORT_POINTS:
        causes.append(f"a short capture: {metrics.n_points} SfM points explain {100 * metrics.coverage:.0f} % of the "
                      "CAD; film more frames that circle the structure (the README gives the smallest capture that "
                      "works), or give picks")
    for c in failed:
        if not c.hint:
            continue
        hint = c.hint
        if not scale and UNIT_HINT in hint:
            hint = hint.replace(f" ({UNIT_HINT})", "").replace(UNIT_HINT, "the CAD's unit")
        if scale and UNIT_HINT in hint:
            hint = hint.replace(f" ({UNIT_HINT})", " (the unit, above)").replace(UNIT_HINT, "the unit, above")
        causes.append(f"{c.name}: {hint}")
    return causes


def format_report(checks: tuple[GateCheck, ...], metrics: AlignMetrics, cad_from_sfm: Sim3, context: str) -> str:
    """A multi-line report: what failed, every gate's numbers, and the likely causes."""
    failed = [c for c in checks if not c.passed]
    head = (f"alignment of {context} failed {len(failed)} quality gate(s): {', '.join(c.name for c in failed)}"
            if failed else f"alignment of {context} passed all quality gates")
    lines = [head, f"  scale {cad_from_sfm.s:.6g} m per SfM unit; {metrics.n_points} points, {metrics.n_roi} in "
                   f"the fitness region ({metrics.n_fitness} counted), {metrics.n_inliers} inliers, coverage "
                   f"{metrics.coverage:.2f}"]
    lines += ["  " + c.line() for c in checks]
    lines += [f"  likely cause {i}: {c}" for i, c in enumerate(likely_causes(failed, metrics), 1)]
    return "\n".join(lines)


def raise_if_failed(checks: tuple[GateCheck, ...], metrics: AlignMetrics, cad_from_sfm: Sim3, context: str) -> None:
    """Raise :class:`AlignmentGateError` with :func:`format_report` if any gate failed."""
    if any(not c.passed for c in checks):
        raise AlignmentGateError(format_report(checks, metrics, cad_from_sfm, context), checks, metrics,
                                 cad_from_sfm)

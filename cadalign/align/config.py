"""Configuration of the CAD <-> SfM alignment stage: frozen dataclasses and the named presets.

Distances of the coarse stages are *relative to the CAD diameter* (the structure can be a 0.5 m valve or
a 15 m frame, and the SfM cloud has no unit until it is aligned); the fine refinement and the quality
gates are in metres, because they describe SfM noise and the accuracy a dataset needs.

Load a config with :func:`cadalign.config.resolve` (preset, then file keys, then overrides)::

    cfg = resolve(AlignConfig, PRESETS, "balanced", path=Path("align.toml"))
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

from cadalign.config import bounded


@dataclass(frozen=True)
class GlobalRegConfig:
    """Coarse alignment without a prior: FPFH features + RANSAC under several scale hypotheses."""

    voxel_rel: float = bounded(0.02, gt=0, lt=0.5)
    """Voxel size for downsampling both clouds, as a fraction of the CAD diameter."""
    normal_radius_vox: float = bounded(2.5, gt=0)
    """Radius of the normal estimation neighbourhood, in voxels."""
    feature_radius_vox: float = bounded(10.0, gt=0)
    """Radius of the FPFH neighbourhood, in voxels."""
    scale_factors: tuple[float, ...] = (0.5, 0.7, 1.0, 1.4, 2.0)
    """Relative scale hypotheses tried around the robust size ratio of the two clouds (the SfM cloud's
    size is inflated or deflated by clutter such as seabed, so one ratio is not enough)."""
    ransac_max_iters: int = bounded(50_000, ge=100)
    """Largest number of RANSAC iterations per scale hypothesis."""
    ransac_confidence: float = bounded(0.999, gt=0, lt=1)
    """RANSAC stops early once it is this confident of its best model."""
    ransac_dist_vox: float = bounded(1.5, gt=0)
    """Inlier distance of RANSAC, in voxels."""
    edge_similarity: float = bounded(0.8, gt=0, lt=1)
    """RANSAC rejects three-point samples whose edge lengths disagree by more than this ratio; it must
    tolerate the scale error left between two scale hypotheses."""
    candidates_per_hypothesis: int = bounded(1, ge=1)
    """RANSAC runs (with different seeds) per scale hypothesis; more is slower but safer."""
    symmetry_variants: bool = True
    """Also try each candidate turned by the 24 rotations mapping the CAD's principal axes onto themselves.
    Man-made structures are often nearly symmetric and features cannot tell the halves apart; a fine score
    can. All 24 are screened cheaply and the best ``variants_refined`` refined and scored."""
    variants_refined: int = bounded(3, ge=1)
    """Turned variants of a candidate refined by ICP and scored (the best of the cheap screen)."""
    variants_of_top: int = bounded(2, ge=1)
    """The turned variants of this many best candidates are tried."""
    polish_rounds: int = bounded(3, ge=1)
    """Rounds of turning the best candidates (a round ends early when the best ones were all turned)."""
    score_dist_rel: float = bounded(0.01, gt=0)
    """Distance (fraction of the CAD diameter) within which a point counts when scoring candidates."""
    score_icp_iters: int = bounded(10, ge=1)
    """Sim(3) ICP iterations per level run on each candidate before scoring it."""
    score_schedule_rel: tuple[float, ...] = (0.1, 0.05, 0.025)
    """Correspondence distances of that short ICP, fractions of the CAD diameter (wide: a coarse
    candidate can be several degrees off)."""
    max_points: int = bounded(5_000, ge=100)
    """Candidates are refined and scored on at most this many SfM points (a seeded random subset)."""
    final_candidates: int = bounded(2, ge=1)
    """This many best distinct candidates (rotations more than 5 degrees apart) each get the full ICP and
    refinement, and the best final fit at the inlier distance wins: the decision between near-symmetric
    look-alikes is taken on all points at full resolution."""
    hypotheses: int = bounded(4, ge=1)
    """This many best distinct candidates (the refined ones first, then the next ones after their short ICP
    only) are kept as hypotheses for the image verification (:mod:`cadalign.align.verify.core`), which moves each
    to the image contours and decides between them: near a small CAD the cloud's ranking can be wrong."""


@dataclass(frozen=True)
class Sim3ICPConfig:
    """Point-to-point ICP with scale: each iteration is a trimmed Umeyama fit on nearest neighbours."""

    corr_dist_schedule_rel: tuple[float, ...] = (0.06, 0.03, 0.015, 0.008)
    """Shrinking largest correspondence distances, fractions of the CAD diameter (coarse to fine)."""
    iters_per_level: int = bounded(20, ge=1)
    """Largest number of iterations at each distance level."""
    trim_keep: float = bounded(0.9, gt=0, le=1)
    """Fraction of the in-range pairs kept each iteration (the rest, with the largest residuals, are
    dropped), so clutter with no CAD counterpart cannot dominate the fit."""
    point_to_plane_targets: bool = True
    """Match each point to the foot of its perpendicular on the nearest sample's tangent plane instead of
    the sample itself: removes the bias of a discrete sampling and converges in fewer iterations."""
    scale_guard: bool = True
    """Bound the scale (see the two fields below). Without it, clutter matched to the nearest CAD surface
    makes each Umeyama step shrink the cloud and the scale can collapse towards 0."""
    max_scale_step: float = bounded(0.02, gt=0)
    """Largest relative scale change per iteration, e.g. 0.02 = 2 percent."""
    scale_range: float = bounded(1.25, gt=1)
    """The scale stays within [s0 / range, s0 * range] of the coarse estimate s0."""
    min_pairs: int = bounded(30, ge=3)
    """Fewest correspondences an iteration needs; fewer ends the level."""
    tol_rel: float = bounded(1e-5, gt=0)
    """A level ends when the step moves points by less than this fraction of the CAD diameter."""
    max_points: int = bounded(60_000, ge=100)
    """ICP runs on at most this many SfM points (a seeded random subset)."""


@dataclass(frozen=True)
class PointToPlaneConfig:
    """Rigid robust point-to-plane ICP (Open3D) after the Sim(3) stage, with its scale held fixed."""

    enabled: bool = True
    """Run this stage at all."""
    max_corr_dist_m: float = bounded(0.15, gt=0)
    """Largest correspondence distance, metres."""
    max_corr_dist_rel: float = bounded(0.05, gt=0)
    """Cap on the correspondence distance and the kernel scale, as a fraction of the CAD diameter (a small
    part, or a CAD read in the wrong unit, must not pair clutter metres away)."""
    kernel: Literal["tukey", "huber"] = "tukey"
    """Robust kernel of the point-to-plane residual."""
    kernel_scale_m: float = bounded(0.05, gt=0)
    """Parameter of the robust kernel (Tukey's c or Huber's k), metres."""
    max_iters: int = bounded(40, ge=1)
    """Largest number of iterations."""


@dataclass(frozen=True)
class GateConfig:
    """Quality gates: an alignment failing any of them raises :class:`~cadalign.errors.AlignmentError`."""

    inlier_dist_m: float = bounded(0.05, gt=0)
    """A point within this distance of the CAD surface is an inlier, metres."""
    inlier_dist_rel: float = bounded(0.02, gt=0)
    """Cap on the inlier distance as a fraction of the CAD diameter (for small parts and unit errors)."""
    roi_dist_m: float = bounded(0.5, gt=0)
    """The fitness region: points within this distance of the CAD surface, or further inside its bounding
    box than this, metres. Seabed and other clutter away from the structure is expected and says nothing
    about the alignment; points well inside the structure's box but off its surface say it is wrong."""
    roi_dist_rel: float = bounded(0.2, gt=0)
    """Cap on ``roi_dist_m`` as a fraction of the CAD diameter."""
    min_fitness: float = bounded(0.6, ge=0, le=1)
    """Smallest fraction of the points in the fitness region that are inliers."""
    fitness_min_views: int = bounded(3, ge=1)
    """The fitness counts the region's points seen in at least this many images (when the cloud says: a COLMAP
    model does); a two-view point scatters along its rays. Fewer than ``min_inliers`` such points: all count.
    See docs/tuning/verify.md#fitness-on-multi-view-points-s56."""
    max_rmse_m: float = bounded(0.03, gt=0)
    """Largest RMS distance of the inliers to the CAD surface, metres."""
    min_rmse_m: float = bounded(2e-4, ge=0)
    """Smallest plausible inlier RMS, metres. Underwater SfM is never this precise: a smaller value
    means the metric scale is far too small (a CAD in millimetres read as metres the other way round)."""
    min_inliers: int = bounded(200, ge=3)
    """Fewest inliers."""
    min_inlier_frac_all: float = bounded(0.05, ge=0, le=1)
    """Fewest inliers as a fraction of the whole cloud (too few points on the structure otherwise)."""
    min_symmetry_margin: float = bounded(0.005, ge=0, lt=1)
    """Global registration only: the final fit of the result must beat the best pose turned more than 5
    degrees away by this fraction (a smaller margin is a coin toss between symmetric look-alikes)."""
    max_scale_change: float = bounded(1.15, ge=1)
    """The final scale must lie within this factor of the coarse (or prior) estimate."""
    cad_size_range_m: tuple[float, float] = (0.05, 100.0)
    """Plausible largest extent of the whole CAD structure, metres (catches mm/m mix-ups)."""
    expected_scale: float | None = None
    """Optional prior on the scale (metres per SfM unit, e.g. from DVL/INS navigation); ``None`` skips."""
    expected_scale_tol: float = bounded(1.5, gt=1)
    """Allowed factor between the final scale and ``expected_scale``."""


@dataclass(frozen=True)
class AlignConfig:
    """CAD <-> SfM registration with scale: coarse (global / picks / prior), Sim(3) ICP, refine, gates."""

    coarse: Literal["auto", "global", "picks", "prior"] = "auto"
    """Coarse method; ``auto`` uses picks if given, else a prior pose if given, else global."""
    cad_samples: int = bounded(60_000, ge=1000)
    """Points sampled (area-weighted) on the CAD surface; the ICP target."""
    seed: int = 0
    """Seed of every random choice (surface sampling, subsets, RANSAC)."""
    global_reg: GlobalRegConfig = field(default_factory=GlobalRegConfig)
    """Global registration knobs."""
    icp: Sim3ICPConfig = field(default_factory=Sim3ICPConfig)
    """Sim(3) ICP knobs."""
    refine: PointToPlaneConfig = field(default_factory=PointToPlaneConfig)
    """Point-to-plane refinement knobs."""
    gates: GateConfig = field(default_factory=GateConfig)
    """Quality gates."""
    figure: bool = True
    """Write ``align.png`` (top and side views of the aligned points coloured by residual)."""


_BALANCED = AlignConfig()

PRESETS: dict[str, AlignConfig] = {
    "fast": replace(
        _BALANCED,
        cad_samples=30_000,
        global_reg=replace(_BALANCED.global_reg, voxel_rel=0.03, feature_radius_vox=6.0,
                           scale_factors=(0.7, 1.0, 1.4), ransac_max_iters=10_000, score_icp_iters=8,
                           variants_refined=2, max_points=3_000),
        icp=replace(_BALANCED.icp, corr_dist_schedule_rel=(0.06, 0.02, 0.008), iters_per_level=12,
                    max_points=20_000),
        refine=replace(_BALANCED.refine, max_iters=15),
    ),
    "balanced": _BALANCED,
    "accurate": replace(
        _BALANCED,
        cad_samples=150_000,
        global_reg=replace(_BALANCED.global_reg, voxel_rel=0.015, feature_radius_vox=12.0,
                           scale_factors=tuple(round(2 ** (k / 3), 3) for k in range(-3, 4)),
                           ransac_max_iters=100_000, candidates_per_hypothesis=2, score_icp_iters=12,
                           variants_refined=4, max_points=8_000, final_candidates=3),
        icp=replace(_BALANCED.icp, corr_dist_schedule_rel=(0.06, 0.03, 0.015, 0.008, 0.004), iters_per_level=30,
                    max_points=200_000),
        refine=replace(_BALANCED.refine, max_iters=80),
    ),
}
"""Named configurations; ``balanced`` is the default."""

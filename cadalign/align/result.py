"""Result dataclasses of the alignment stage."""

from __future__ import annotations

from dataclasses import dataclass

from cadalign.types import Sim3


@dataclass(frozen=True)
class IcpStep:
    """One ICP iteration.

    Attributes:
        stage: ``sim3`` (point-to-point with scale) or ``refine`` (rigid point-to-plane, summary only).
        level: index of the correspondence-distance level.
        iteration: iteration within the level.
        max_dist_m: largest correspondence distance used, metres.
        n_pairs: correspondences used in the fit (after trimming).
        rmse_m: RMS residual of those correspondences, metres (``sim3``: before the step, point-to-plane
            when ``point_to_plane_targets``; ``refine``: Open3D's point-to-point inlier RMSE after it).
        scale: the scale ``s`` of ``cad_from_sfm`` after the step.
        scale_clamped: whether the scale guard limited this step.
    """

    stage: str
    level: int
    iteration: int
    max_dist_m: float
    n_pairs: int
    rmse_m: float
    scale: float
    scale_clamped: bool = False


@dataclass(frozen=True)
class GateCheck:
    """One quality gate: the measured value against its threshold."""

    name: str
    value: float
    threshold: float | tuple[float, float]
    op: str
    """How ``value`` must compare to ``threshold``: ``>=``, ``<=`` or ``in``."""
    passed: bool
    hint: str = ""
    """Likely causes when it fails."""

    def line(self) -> str:
        thr = f"[{self.threshold[0]:.4g}, {self.threshold[1]:.4g}]" if isinstance(self.threshold, tuple) else (
            f"{self.threshold:.4g}")
        mark = "ok  " if self.passed else "FAIL"
        return f"{mark} {self.name} = {self.value:.4g} (must be {self.op} {thr})"


@dataclass(frozen=True)
class AlignMetrics:
    """Residual statistics of the SfM points against the CAD surface after alignment.

    Attributes:
        fitness: inliers / points in the fitness region (near the CAD surface or well inside its box).
        inlier_rmse_m: RMS distance of the inliers to the CAD surface, metres.
        n_inliers: points within the inlier distance of the CAD surface.
        n_roi: points in the fitness region.
        n_points: all (finite) SfM points.
        coverage: fraction of CAD samples with an inlier within the inlier distance (how much of the
            structure the cloud explains; low for a partial survey, which is not an error).
        median_residual_m: median distance of the fitness-region points to the CAD surface, metres.
        n_fitness: fitness-region points the fitness counts (those seen in enough images, when known).
    """

    fitness: float
    inlier_rmse_m: float
    n_inliers: int
    n_roi: int
    n_points: int
    coverage: float
    median_residual_m: float
    n_fitness: int = 0


@dataclass(frozen=True)
class AlignResult:
    """The outcome of a successful (gated) alignment.

    Attributes:
        cad_from_sfm: similarity mapping SfM coordinates into CAD/world metres.
        coarse_from: which coarse method produced the start (``global``, ``picks`` or ``prior``).
        coarse: the coarse estimate of ``cad_from_sfm``.
        metrics: residual statistics after alignment.
        gates: every gate with its value and threshold (all passed; ``align.json`` drops their hints).
        seconds: wall time per stage (``sample``, ``coarse``, ``sim3_icp``, ``refine``, ``gates``).
        history: the ICP iterations, in order.
        global_scores: for a global coarse estimate, the final fit score (F-score of precision and
            coverage at the inlier distance) of the result and of the best refined pose turned more than
            5 degrees away (0 if none); close values mean a near-symmetric, ambiguous structure.
        hypotheses: ``(cad_from_sfm, final fit score)`` of every refined pose, best fit first (the result is
            the first), then of the next distinct global candidates after their short ICP only (up to
            ``global_reg.hypotheses`` in all): what the image verification (:mod:`cadalign.align.verify.core`)
            judges again.
    """

    cad_from_sfm: Sim3
    coarse_from: str
    coarse: Sim3
    metrics: AlignMetrics
    gates: tuple[GateCheck, ...]
    seconds: dict[str, float]
    history: tuple[IcpStep, ...]
    global_scores: tuple[float, float] | None = None
    hypotheses: tuple[tuple[Sim3, float], ...] = ()

    @property
    def scale(self) -> float:
        """Metres per SfM unit."""
        return self.cad_from_sfm.s

    @property
    def fitness(self) -> float:
        return self.metrics.fitness

    @property
    def inlier_rmse_m(self) -> float:
        return self.metrics.inlier_rmse_m

    @property
    def n_inliers(self) -> int:
        return self.metrics.n_inliers

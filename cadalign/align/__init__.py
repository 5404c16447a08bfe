"""CAD <-> SfM registration with scale: ``cad_from_sfm`` (SfM coordinates -> CAD/world metres) + quality.

Pipeline: a coarse estimate (global FPFH + RANSAC over scale hypotheses and symmetric turns, 3+ user
picks, or a prior pose), Sim(3) ICP with a scale guard and a shrinking correspondence distance, rigid
robust point-to-plane refinement with the scale fixed, then quality gates that raise
:class:`AlignmentGateError` (an :class:`~cadalign.errors.AlignmentError`) with a readable report.

Example:
    >>> from cadalign.align import PRESETS, align, run  # doctest: +SKIP
    >>> result = align(points_sfm, [(frame_model, T_world_from_frame)], PRESETS["fast"])  # doctest: +SKIP
    >>> run(PRESETS["balanced"], "sparse/0", ["frame.obj"], "runs/align")  # doctest: +SKIP
"""

from cadalign.align.config import PRESETS, AlignConfig, GateConfig, GlobalRegConfig, PointToPlaneConfig, Sim3ICPConfig
from cadalign.align.core import align
from cadalign.align.gates import AlignmentGateError, check_gates, measure
from cadalign.align.global_reg import Candidate, global_registration
from cadalign.align.icp import refine_point_to_plane, sim3_icp
from cadalign.align.picks import Picks, parse_picks, read_picks, sim3_from_picks
from cadalign.align.result import AlignMetrics, AlignResult, GateCheck, IcpStep
from cadalign.align.run import ALIGN_JSON, ALIGN_PNG, load_points, read_sim3, run
from cadalign.align.surface import CadPart, CadSurface, sample_surface

__all__ = [
    "ALIGN_JSON",
    "ALIGN_PNG",
    "PRESETS",
    "AlignConfig",
    "AlignMetrics",
    "AlignResult",
    "AlignmentGateError",
    "CadPart",
    "CadSurface",
    "Candidate",
    "GateCheck",
    "GateConfig",
    "GlobalRegConfig",
    "IcpStep",
    "Picks",
    "PointToPlaneConfig",
    "Sim3ICPConfig",
    "align",
    "check_gates",
    "global_registration",
    "load_points",
    "measure",
    "parse_picks",
    "read_picks",
    "read_sim3",
    "refine_point_to_plane",
    "run",
    "sample_surface",
    "sim3_from_picks",
    "sim3_icp",
]

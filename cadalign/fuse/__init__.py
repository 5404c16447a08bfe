"""Semantic 3D maps: TSDF (Open3D voxel blocks) or surfels, with Bayesian class fusion.

Pipeline: posed frames (depth in metres + class probabilities) -> :class:`SemanticTSDF` or :class:`SurfelMap`
(``integrate`` per frame) -> labelled mesh / point cloud / map file. The stage entry point is
:func:`cadalign.fuse.run.run`; ``cadalign fuse`` is its command line.
"""

from cadalign.fuse.base import FuseFrame, LabelledGeometry, SemanticMap
from cadalign.fuse.config import PRESETS, FuseConfig
from cadalign.fuse.surfel import SurfelMap
from cadalign.fuse.tsdf import SemanticTSDF

__all__ = ["PRESETS", "FuseConfig", "FuseFrame", "LabelledGeometry", "SemanticMap", "SemanticTSDF", "SurfelMap"]

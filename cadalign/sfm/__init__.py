"""Structure from motion for ROV video: frames, pycolmap presets, report and projected sparse depth.

A notebook runs the stage in two lines::

    from cadalign.sfm import PRESETS, run
    out = run(PRESETS["balanced"], "dive.mp4", "runs/dive/sfm")

Importing this package does not import pycolmap; the steps import it when they run.
"""

from cadalign.sfm.config import (
    PRESETS,
    CameraConfig,
    DepthConfig,
    FeatureConfig,
    FrameConfig,
    MapperConfig,
    MatchConfig,
    SfMConfig,
)
from cadalign.sfm.pipeline import run

__all__ = [
    "PRESETS",
    "CameraConfig",
    "DepthConfig",
    "FeatureConfig",
    "FrameConfig",
    "MapperConfig",
    "MatchConfig",
    "SfMConfig",
    "run",
]

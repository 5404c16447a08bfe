"""The dataset builder (:mod:`cadalign.build.run`: frames -> SfM -> CAD alignment -> BOP dataset, and its report
against a simulation's truth, :mod:`cadalign.build.report`) and its scale-out: frame jobs and the executors that run
them (``local`` or Ray), and many videos as one build each (:mod:`cadalign.build.videos`).

Importing this package never imports Ray; only :class:`~cadalign.build.executor.RayExecutor` does, when it
renders.
"""

from cadalign.build.executor import ExecutorConfig, RayExecutor, executor_config, make_executor
from cadalign.build.frames import CameraModel, FrameJob, FrameShared, render_chunk, write_frame
from cadalign.build.videos import VideoJob, VideoResult, build_videos, read_jobs

__all__ = ["CameraModel", "ExecutorConfig", "FrameJob", "FrameShared", "RayExecutor", "VideoJob", "VideoResult",
           "build_videos", "executor_config", "make_executor", "read_jobs", "render_chunk", "write_frame"]

"""Scale-out of the dataset build: frame jobs and the executors that run them (``local`` or Ray), and many
videos as one build each (:mod:`cadalign.scale.videos`).

Importing this package never imports Ray; only :class:`~cadalign.scale.executor.RayExecutor` does, when it
renders.
"""

from cadalign.scale.executor import ExecutorConfig, RayExecutor, executor_config, make_executor
from cadalign.scale.frames import CameraModel, FrameJob, FrameShared, render_chunk, write_frame
from cadalign.scale.videos import VideoJob, VideoResult, build_videos, read_jobs

__all__ = ["CameraModel", "ExecutorConfig", "FrameJob", "FrameShared", "RayExecutor", "VideoJob", "VideoResult",
           "build_videos", "executor_config", "make_executor", "read_jobs", "render_chunk", "write_frame"]

"""Scale-out of the dataset build: frame jobs and the executors that run them (``local`` or Ray).

Importing this package never imports Ray; only :class:`~cadalign.scale.executor.RayExecutor` does, when it
renders.
"""

from cadalign.scale.executor import ExecutorConfig, RayExecutor, executor_config, make_executor
from cadalign.scale.frames import CameraModel, FrameJob, FrameShared, render_chunk, write_frame

__all__ = ["CameraModel", "ExecutorConfig", "FrameJob", "FrameShared", "RayExecutor", "executor_config",
           "make_executor", "render_chunk", "write_frame"]

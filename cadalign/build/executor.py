"""Where the dataset build renders its frames: in the builder's process (``local``) or on Ray (``ray``).

``local`` (the default) is the builder's own loop and never imports Ray. ``ray`` sends chunks of
:class:`~cadalign.build.frames.FrameJob` to Ray tasks: the meshes and camera models go into the object store
once (``ray.put``), each task builds its ray-casting scene once and writes its frames straight to the
dataset folder, and returns only the frame ids it wrote, so the driver's memory stays bounded by the number
of tasks in flight (``--workers``, default 2 per CPU), not by the length of the video. A task whose worker
dies (killed, out of memory, node lost) is retried by Ray (``max_retries``); the retry skips the frames whose
record is on disk and rewrites the others completely (see :mod:`cadalign.build.frames`), so the result is the same
files as an uninterrupted or a local build. Errors raised by the code (a bad input) are not retried.

Cluster use: ``address`` (or the ``RAY_ADDRESS`` environment variable) names a running cluster, e.g.
``ray://head:10001`` or ``head:6379``; cadalign must be installed on every node and the output folder must
be on storage that every node reaches under the same path.
"""

from __future__ import annotations

import importlib.util
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from cadalign.build.frames import FrameJob, FrameShared, render_chunk
from cadalign.config import bounded
from cadalign.errors import ConfigError
from cadalign.types import Progress

log = logging.getLogger(__name__)
ChunkFn = Callable[[Sequence[FrameJob], FrameShared], list[int]]
KINDS = ("local", "ray")


@dataclass(frozen=True)
class ExecutorConfig:
    kind: Literal["local", "ray"] = "local"
    """``local``: render in the builder's process (no Ray import); ``ray``: Ray tasks, local or on a cluster."""
    address: str | None = None
    """Ray cluster address (``ray://head:10001``, ``head:6379`` or ``auto``); None: ``RAY_ADDRESS`` if set,
    else a Ray instance started on this machine for the build and stopped after it."""
    workers: int | None = bounded(None, ge=1)
    """Local Ray: its CPUs; both local and cluster: the most tasks in flight (queued or running) at once.
    None: every CPU of this machine for a local instance, and 2 tasks per CPU of the Ray instance in flight."""
    frames_per_task: int = bounded(4, ge=1)
    """Frames per Ray task: each task builds its ray-casting scene once (~0.2 s for the default scene)."""
    max_retries: int = bounded(3, ge=0)
    """Retries of a task whose worker process died (system failures only, not errors in the code)."""
    object_store_mb: int = bounded(256, ge=64)
    """Object store of a local Ray instance, MiB (it holds the meshes and camera models; spills to disk)."""


def executor_config(kind: str, address: str | None = None, workers: int | None = None) -> ExecutorConfig:
    """Validated config from the CLI's ``--executor``, ``--ray-address`` and ``--workers``."""
    if kind not in KINDS:
        raise ConfigError(f"unknown executor {kind!r}; allowed values: {', '.join(KINDS)}")
    if kind == "local" and address:
        raise ConfigError("--ray-address needs --executor ray")
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be at least 1, got {workers}")
    return ExecutorConfig(kind, address or None, workers)  # type: ignore[arg-type]


def chunks(jobs: Sequence[FrameJob], size: int) -> list[list[FrameJob]]:
    """Consecutive chunks of at most ``size`` jobs, in order."""
    return [list(jobs[i : i + size]) for i in range(0, len(jobs), size)]


class RayExecutor:
    """Renders frame jobs with Ray tasks (see the module docstring); ``chunk_fn`` is the task body (tests
    wrap it to inject worker failures)."""

    def __init__(self, cfg: ExecutorConfig, chunk_fn: ChunkFn = render_chunk) -> None:
        if cfg.kind != "ray":
            raise ConfigError(f"RayExecutor needs kind='ray', got {cfg.kind!r}")
        self.cfg = cfg
        self.chunk_fn = chunk_fn

    def render(self, jobs: Sequence[FrameJob], shared: FrameShared, progress: Progress | None = None) -> list[int]:
        """Render and write ``jobs``; returns the frame ids written (sorted). Blocks until all are done."""
        import ray  # lazy: optional dependency (ray)

        if not jobs:
            return []
        started = ensure_ray(self.cfg)
        try:
            done = self._run(ray, jobs, shared, progress)
        finally:
            if started:
                ray.shutdown()
        return sorted(done)

    def _run(self, ray: Any, jobs: Sequence[FrameJob], shared: FrameShared, progress: Progress | None) -> list[int]:
        work = chunks(jobs, self.cfg.frames_per_task)
        cpus = int(ray.cluster_resources().get("CPU", 1))
        window = self.cfg.workers or 2 * cpus  # tasks in flight: an explicit cap, else 2 per CPU (none idles)
        task = ray.remote(num_cpus=1, max_retries=self.cfg.max_retries, retry_exceptions=False)(self.chunk_fn)
        shared_ref = ray.put(shared)
        log.info("ray: %d frames in %d tasks, at most %d in flight on %d CPUs", len(jobs), len(work), window, cpus)
        completed = ray_map(ray, task, [(chunk, shared_ref) for chunk in work], window)
        done: list[int] = []
        for ids in progress(completed, "render (ray)", len(work)) if progress else completed:
            done.extend(ids)
        return done


def ray_map(ray: Any, task: Any, args: Sequence[tuple], window: int) -> Iterator[Any]:
    """Results of ``task.remote(*a)`` for each ``a`` in ``args``, in completion order, with at most ``window``
    tasks in flight (the driver holds at most ``window`` references and results at a time)."""
    pending: list[Any] = []
    for a in args:
        pending.append(task.remote(*a))
        if len(pending) >= window:
            ready, pending = ray.wait(pending, num_returns=1)
            yield ray.get(ready[0])
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        yield ray.get(ready[0])


def ensure_ray(cfg: ExecutorConfig) -> bool:
    """Connect to (or start) Ray; True when this call started it (the caller then shuts it down)."""
    import ray  # lazy: optional dependency (ray)

    if ray.is_initialized():
        return False
    address = cfg.address or os.environ.get("RAY_ADDRESS") or None
    if address:
        log.info("connecting to the Ray cluster at %s", address)
        try:
            ray.init(address=address, log_to_driver=False)
        except (ConnectionError, TimeoutError, RuntimeError, ValueError) as exc:
            raise ConfigError(f"cannot connect to the Ray cluster at {address!r} ({type(exc).__name__}: {exc}); "
                              "check the address (ray://HEAD:10001 or HEAD:6379, or RAY_ADDRESS) and that the "
                              "cluster is up, or use --executor local") from exc
    else:
        cpus = cfg.workers or os.cpu_count() or 1
        log.info("starting a local Ray instance with %d CPUs", cpus)
        ray.init(num_cpus=cpus, include_dashboard=False, object_store_memory=cfg.object_store_mb * 2**20,
                 log_to_driver=False)
    return True


def make_executor(cfg: ExecutorConfig) -> RayExecutor | None:
    """The executor for ``cfg``: None for ``local`` (the builder renders in its own loop), else Ray's.

    Raises:
        ConfigError: ``ray`` without Ray installed (checked before any work, without importing it).
    """
    if cfg.kind == "local":
        return None
    if importlib.util.find_spec("ray") is None:
        raise ConfigError("--executor ray needs Ray, which is not installed: pip install 'cadalign[ray]' "
                          "(or use --executor local)")
    return RayExecutor(cfg)

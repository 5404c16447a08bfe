"""Many videos: one dataset build per video, each a Ray task (frames, SfM, alignment and rendering inside).

A jobs file (TOML/YAML) lists the videos::

    [[video]]
    source = "dive_0412.mp4"          # a video or a folder of frames; relative to this file
    init = "dive_0412_picks.json"     # optional: picks, calib, gt, cad, cad_unit, name

    [[video]]
    source = "dive_0413.mp4"

``cadalign build-dataset JOBS.toml --cad CAD --out ROOT [--executor ray]`` builds each into ``ROOT/<name>/``
(name: the source's stem unless given), with the command's ``--cad``/``--calib``/``--cad-unit`` as defaults.
With Ray every video is one task (``num_cpus=1``; a video's SfM is the long part), at most ``--workers`` (default:
one per CPU) at a time; a task whose worker dies is retried and resumes where the build stopped (the stages
skip finished work). A video whose build fails with the project's error (a failed alignment, a bad input) is
reported and the others go on; ``ROOT/videos_report.json`` lists every video's outcome.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from cadalign.build.executor import ExecutorConfig, ensure_ray, ray_map
from cadalign.build.run import build_dataset
from cadalign.config import read_mapping
from cadalign.errors import CadalignError, ConfigError
from cadalign.io import read_json, write_json
from cadalign.types import Progress

log = logging.getLogger(__name__)
JOB_KEYS = ("source", "name", "cad", "init", "calib", "gt", "cad_unit")
JOBS_SUFFIXES = (".toml", ".yaml", ".yml")
REPORT = "videos_report.json"


@dataclass(frozen=True)
class VideoJob:
    """One video's build (paths absolute)."""

    name: str
    """Output sub-folder of ROOT."""
    source: Path
    """Video file or folder of frames."""
    cad: Path
    """Scene spec or CAD mesh."""
    init: Path | None = None
    """Picks for the coarse alignment."""
    calib: Path | None = None
    """Known intrinsics."""
    gt: Path | None = None
    """Simulator output to report errors against."""
    cad_unit: str | None = None
    """Unit of a CAD mesh file."""


@dataclass(frozen=True)
class VideoResult:
    name: str
    """The job's name."""
    out: str
    """Its build folder."""
    ok: bool
    """Whether the build finished."""
    frames: int
    """Frames in the dataset (0 on failure)."""
    error: str | None
    """The error that stopped it, else None."""


def read_jobs(path: Path, *, cad: Path | None = None, calib: Path | None = None,
              cad_unit: str | None = None) -> list[VideoJob]:
    """The video jobs of a jobs file; ``cad``/``calib``/``cad_unit`` are the defaults of every job.

    Raises:
        ConfigError: unknown keys, no ``[[video]]`` entries, a missing source or cad, or two jobs with one name.
    """
    path = Path(path)
    data = read_mapping(path)
    if set(data) != {"video"} or not isinstance(data["video"], list) or not data["video"]:
        raise ConfigError(f"{path}: expected only [[video]] entries (keys: {', '.join(JOB_KEYS)}), got keys "
                          f"{sorted(data)}")
    base = path.parent

    def resolve(v: Any) -> Path | None:
        return None if v is None else (base / str(v)).resolve()

    jobs: list[VideoJob] = []
    for i, entry in enumerate(data["video"]):
        unknown = sorted(set(entry) - set(JOB_KEYS)) if isinstance(entry, dict) else ["(not a table)"]
        if unknown or "source" not in entry:
            raise ConfigError(f"{path}: video {i + 1}: unknown keys {unknown} or no 'source'; allowed keys: "
                              f"{', '.join(JOB_KEYS)}")
        job_cad = resolve(entry.get("cad")) or (Path(cad).resolve() if cad is not None else None)
        if job_cad is None:
            raise ConfigError(f"{path}: video {i + 1} has no 'cad' and no --cad was given")
        src = resolve(entry["source"])
        assert src is not None
        jobs.append(VideoJob(str(entry.get("name") or src.stem), src, job_cad, resolve(entry.get("init")),
                             resolve(entry.get("calib")) or (Path(calib).resolve() if calib else None),
                             resolve(entry.get("gt")), entry.get("cad_unit", cad_unit)))
    names = [j.name for j in jobs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"{path}: two videos would be built into the same folder {dup}; give them distinct 'name's")
    return jobs


def build_one(job: VideoJob, root: Path, preset: str, overwrite: bool) -> VideoResult:
    """Build ``job`` into ``root/<name>`` (rendering in this process); the project's errors become a result."""

    out = Path(root) / job.name
    try:
        build_dataset(job.source, job.cad, out, preset=preset, picks=job.init, gt=job.gt, cad_unit=job.cad_unit,
                      calib=job.calib, overwrite=overwrite)
    except CadalignError as exc:
        log.error("video %s failed: %s", job.name, exc)
        return VideoResult(job.name, str(out), False, 0, f"{type(exc).__name__}: {exc}")
    return VideoResult(job.name, str(out), True, int(read_json(out / "build_report.json")["frames"]), None)


def build_videos(jobs: Sequence[VideoJob], root: Path, cfg: ExecutorConfig, *, preset: str = "balanced",
                 overwrite: bool = False, progress: Progress | None = None,
                 build_fn: Callable[[VideoJob, Path, str, bool], VideoResult] = build_one) -> list[VideoResult]:
    """Build every job (one after another, or one Ray task each); writes ``root/videos_report.json``."""
    root = Path(root)
    args = [(job, root, preset, overwrite) for job in jobs]
    if cfg.kind == "local":
        items = progress(args, "videos", len(args)) if progress else args
        results = [build_fn(*a) for a in items]
    else:
        import ray  # lazy: optional dependency (ray)

        started = ensure_ray(cfg)
        try:
            window = cfg.workers or int(ray.cluster_resources().get("CPU", 1))
            task = ray.remote(num_cpus=1, max_retries=cfg.max_retries, retry_exceptions=False)(build_fn)
            done = ray_map(ray, task, args, window)
            results = list(progress(done, "videos (ray)", len(args)) if progress else done)
        finally:
            if started:
                ray.shutdown()
    results.sort(key=lambda r: [j.name for j in jobs].index(r.name))
    write_json(root / REPORT, {"videos": [asdict(r) for r in results],
                               "failed": [r.name for r in results if not r.ok]})
    return results

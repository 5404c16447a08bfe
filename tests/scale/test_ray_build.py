"""``build-dataset --executor ray`` on local Ray (2 worker CPUs) writes the same bytes as the local build,
also when a worker process is killed in the middle of a frame (Ray retries its task).

The tests that need no running Ray come first: the module's Ray instance (``ray_two_cpus``) lives from the
first test that uses it to the end of the module."""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest
from scale_testdata import dataset_bytes, fresh_out, write_jobs
from typer.testing import CliRunner

from cadalign.build import ExecutorConfig, FrameJob, FrameShared, RayExecutor, render_chunk
from cadalign.cli.main import app
from cadalign.io import read_json

ray = pytest.importorskip("ray")

RAY_ENV = {"RAY_AUTH_MODE": "disabled", "RAY_USAGE_STATS_ENABLED": "0"}  # a private local instance: no token


@pytest.fixture(scope="module")
def quiet_ray_env() -> Iterator[None]:
    old = {k: os.environ.get(k) for k in RAY_ENV}
    os.environ.update(RAY_ENV)
    yield
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@pytest.fixture(scope="module")
def ray_two_cpus(quiet_ray_env: None) -> Iterator[None]:
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=200 * 2**20, log_to_driver=False)
    yield
    ray.shutdown()


def _cli_build(local_build: Path, capture: tuple[Path, Path], out: Path) -> None:
    spec, sim = capture
    fresh_out(local_build, out)
    res = CliRunner().invoke(app, ["build-dataset", str(sim / "frames"), "--cad", str(spec), "--out", str(out),
                                   "--preset", "fast", "--init", str(local_build / "picks.json"), "--executor", "ray",
                                   "--workers", "2"])
    assert res.exit_code == 0, res.output
    assert dataset_bytes(out) == dataset_bytes(local_build)


@pytest.mark.slow
def test_cli_ray_executor_starts_and_stops_its_own_ray(local_build: Path, scale_capture: tuple[Path, Path],
                                                       tmp_path: Path, quiet_ray_env: None) -> None:
    """No Ray running: the CLI starts a 2-CPU local instance, renders, shuts it down; same bytes as local
    (slow: a second Ray start, ~10 s here)."""
    assert not ray.is_initialized()
    _cli_build(local_build, scale_capture, tmp_path / "cli")
    assert not ray.is_initialized()


HEAD = """
import os, sys
import ray
ray.init(num_cpus=2, include_dashboard=False, object_store_memory=200 * 2**20, log_to_driver=False)
print(ray.get_runtime_context().gcs_address, flush=True)
sys.stdin.read()  # keep the instance up until the test closes our stdin
ray.shutdown()
"""


@pytest.mark.slow
def test_cli_connects_to_a_running_cluster_by_address(local_build: Path, scale_capture: tuple[Path, Path],
                                                      tmp_path: Path, quiet_ray_env: None) -> None:
    """A Ray instance owned by another process (a one-node "cluster"): ``--ray-address`` connects to it, the
    frames are rendered by its workers, the CLI disconnects and leaves it running (slow: two Ray starts)."""
    import subprocess
    import sys

    assert not ray.is_initialized()
    head = subprocess.Popen([sys.executable, "-c", HEAD], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        address = head.stdout.readline().strip()  # type: ignore[union-attr]
        assert ":" in address, address
        spec, sim = scale_capture
        out = fresh_out(local_build, tmp_path / "cluster")
        res = CliRunner().invoke(app, ["build-dataset", str(sim / "frames"), "--cad", str(spec), "--out", str(out),
                                       "--preset", "fast", "--init", str(local_build / "picks.json"),
                                       "--executor", "ray", "--ray-address", address])
        assert res.exit_code == 0, res.output
        assert not ray.is_initialized() and head.poll() is None
        assert dataset_bytes(out) == dataset_bytes(local_build)
    finally:
        head.communicate(input="", timeout=60)
    assert head.returncode == 0


def test_cli_ray_executor_uses_the_running_ray(local_build: Path, scale_capture: tuple[Path, Path], tmp_path: Path,
                                               ray_two_cpus: None) -> None:
    """Ray already running (as after ``ray.init(address=...)``): the CLI uses it and leaves it running."""
    _cli_build(local_build, scale_capture, tmp_path / "cli")
    assert ray.is_initialized()


def _build(local_build: Path, capture: tuple[Path, Path], out: Path, executor: RayExecutor) -> Path:
    from cadalign.build.run import build_dataset

    spec, sim = capture
    fresh_out(local_build, out)
    return build_dataset(sim / "frames", spec, out, preset="fast", picks=local_build / "picks.json", executor=executor)


def test_ray_build_is_byte_identical_to_local(local_build: Path, scale_capture: tuple[Path, Path], tmp_path: Path,
                                              ray_two_cpus: None) -> None:
    ref = dataset_bytes(local_build)
    assert len([k for k in ref if k.startswith("all/000000/depth/")]) == 12
    out = _build(local_build, scale_capture, tmp_path / "ray", RayExecutor(ExecutorConfig("ray", frames_per_task=2)))
    got = dataset_bytes(out)
    assert sorted(got) == sorted(ref)
    assert [k for k in ref if got[k] != ref[k]] == []
    assert read_json(out / "build_report.json")["frames"] == 12


def test_killed_worker_mid_frame_gives_the_same_dataset(local_build: Path, scale_capture: tuple[Path, Path],
                                                        tmp_path: Path, ray_two_cpus: None) -> None:
    """The task holding frames 4-5 writes frame 4, tears frame 5's depth PNG and SIGKILLs its own worker on
    its first attempt; Ray retries it on a new worker, which skips frame 4 and rewrites frame 5."""
    marker, pids = tmp_path / "killed", tmp_path / "pids"
    pids.mkdir()

    def flaky_chunk(jobs: Sequence[FrameJob], shared: FrameShared) -> list[int]:
        (pids / str(os.getpid())).touch()
        if jobs[0].k == 4 and not marker.exists():
            marker.touch()
            render_chunk(jobs[:1], shared)
            (shared.scene_dir / "depth").mkdir(parents=True, exist_ok=True)
            (shared.scene_dir / "depth" / "000005.png").write_bytes(b"torn")
            os.kill(os.getpid(), signal.SIGKILL)
        return render_chunk(jobs, shared)

    executor = RayExecutor(ExecutorConfig("ray", frames_per_task=2, max_retries=2), chunk_fn=flaky_chunk)
    out = _build(local_build, scale_capture, tmp_path / "ray_kill", executor)
    assert marker.is_file()
    assert len(list(pids.iterdir())) >= 2  # the killed worker and at least one other process ran tasks
    got, ref = dataset_bytes(out), dataset_bytes(local_build)
    assert sorted(got) == sorted(ref)  # no duplicate, temporary or missing file
    assert [k for k in ref if got[k] != ref[k]] == []


def test_errors_in_the_code_are_not_retried(local_build: Path, scale_capture: tuple[Path, Path], tmp_path: Path,
                                            ray_two_cpus: None) -> None:
    """An exception raised by the task (a bad input, a bug) reaches the caller as itself after one attempt."""
    calls = tmp_path / "calls"
    calls.mkdir()

    def failing_chunk(jobs: Sequence[FrameJob], shared: FrameShared) -> list[int]:
        (calls / f"{jobs[0].k}_{os.getpid()}_{len(list(calls.iterdir()))}").touch()
        if jobs[0].k == 0:
            raise FileNotFoundError("frame 0 source missing")
        return render_chunk(jobs, shared)

    executor = RayExecutor(ExecutorConfig("ray", frames_per_task=6, max_retries=3), chunk_fn=failing_chunk)
    with pytest.raises(FileNotFoundError, match="frame 0 source missing"):
        _build(local_build, scale_capture, tmp_path / "ray_err", executor)
    assert len([p for p in calls.iterdir() if p.name.startswith("0_")]) == 1



def test_many_videos_one_ray_task_each(local_build: Path, scale_capture: tuple[Path, Path], tmp_path: Path,
                                       ray_two_cpus: None) -> None:
    """Two videos of a jobs file: each is built in a Ray worker (not this process) into ROOT/<name>/, with
    the reference bytes, and the report lists both."""
    from cadalign.build.videos import VideoJob, VideoResult, build_one, build_videos, read_jobs

    spec, sim = scale_capture
    root, pids = tmp_path / "root", tmp_path / "pids"
    pids.mkdir()
    for name in ("a", "b"):
        fresh_out(local_build, root / name)
    jobs = read_jobs(write_jobs(tmp_path / "jobs.toml", [
        {"source": str(sim / "frames"), "name": n, "init": str(local_build / "picks.json")} for n in ("a", "b")]),
        cad=spec)

    def traced(job: VideoJob, root: Path, preset: str, overwrite: bool) -> VideoResult:
        (pids / f"{job.name}_{os.getpid()}").touch()
        return build_one(job, root, preset, overwrite)

    results = build_videos(jobs, root, ExecutorConfig("ray"), preset="fast", build_fn=traced)
    assert [(r.name, r.ok, r.frames) for r in results] == [("a", True, 12), ("b", True, 12)]
    assert {p.name.split("_")[0] for p in pids.iterdir()} == {"a", "b"}
    assert all(int(p.name.split("_")[1]) != os.getpid() for p in pids.iterdir())
    assert read_json(root / "videos_report.json")["failed"] == []
    for name in ("a", "b"):
        assert dataset_bytes(root / name) == dataset_bytes(local_build)

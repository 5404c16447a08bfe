"""Executor choice and its CLI options; the default local build never imports Ray."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scale_testdata import dataset_bytes, fresh_out, jobs_args, write_jobs
from typer.testing import CliRunner

from cadalign.build import ExecutorConfig, RayExecutor, executor_config, make_executor
from cadalign.build.executor import chunks
from cadalign.build.frames import CameraModel
from cadalign.cli.main import app
from cadalign.errors import ConfigError
from cadalign.io import read_json


def test_executor_config_from_cli_values() -> None:
    assert executor_config("local") == ExecutorConfig()
    assert make_executor(executor_config("local")) is None
    cfg = executor_config("ray", "ray://head:10001", 8)
    assert (cfg.kind, cfg.address, cfg.workers) == ("ray", "ray://head:10001", 8)
    assert isinstance(make_executor(cfg), RayExecutor)
    assert executor_config("ray", "").address is None


@pytest.mark.parametrize(("args", "message"), [
    (("dask",), "unknown executor 'dask'; allowed values: local, ray"),
    (("local", "head:6379"), "--ray-address needs --executor ray"),
    (("ray", None, 0), "--workers must be at least 1, got 0"),
])
def test_executor_config_refuses_bad_values(args: tuple, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        executor_config(*args)


def test_ray_executor_without_ray_installed_is_refused_before_any_work(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a))
    with pytest.raises(ConfigError, match=r"needs Ray, which is not installed: pip install 'cadalign\[ray\]'"):
        make_executor(executor_config("ray"))
    assert make_executor(executor_config("local")) is None


def test_unreachable_cluster_is_a_config_error_naming_the_address(monkeypatch: pytest.MonkeyPatch) -> None:
    """Ray's own connection error (after its retries) becomes the project's error with the fix."""
    ray = pytest.importorskip("ray")
    from cadalign.build.executor import ensure_ray

    def refuse(**kwargs: object) -> None:
        raise ConnectionError(f"could not reach {kwargs['address']}")

    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", refuse)
    monkeypatch.setenv("RAY_ADDRESS", "head:6379")
    with pytest.raises(ConfigError, match=r"cannot connect to the Ray cluster at 'head:6379' \(ConnectionError"):
        ensure_ray(ExecutorConfig("ray"))
    with pytest.raises(ConfigError, match="'ray://other:10001'"):
        ensure_ray(ExecutorConfig("ray", address="ray://other:10001"))


def test_ray_executor_refuses_a_local_config() -> None:
    with pytest.raises(ConfigError, match="kind='ray'"):
        RayExecutor(ExecutorConfig())


@settings(max_examples=25, deadline=None)
@given(n=st.integers(0, 40), size=st.integers(1, 9))
def test_chunks_keep_order_and_size(n: int, size: int) -> None:
    jobs = list(range(n))
    parts = chunks(jobs, size)  # type: ignore[arg-type]
    assert [j for p in parts for j in p] == jobs
    assert len(parts) == math.ceil(n / size) and all(1 <= len(p) <= size for p in parts)


def test_camera_model_rebuilds_the_same_rays() -> None:
    import pycolmap

    from cadalign.align.camera_refine import rays_of

    cam = pycolmap.Camera(model="SIMPLE_RADIAL", width=8, height=6, params=[7.5, 4.0, 3.0, -0.05])
    model = CameraModel.of(cam)
    assert model == CameraModel("SIMPLE_RADIAL", 8, 6, (7.5, 4.0, 3.0, -0.05))
    assert np.array_equal(model.rays_cam(), rays_of(cam)) and model.rays_cam().shape == (6, 8, 3)


def test_cli_help_lists_the_executor_options() -> None:
    res = CliRunner().invoke(app, ["build-dataset", "--help"], terminal_width=200)
    assert res.exit_code == 0
    for opt in ("--executor", "--ray-address", "--workers", "RAY_ADDRESS"):
        assert opt in res.output


def test_cli_refuses_an_unknown_executor_before_any_work(tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["build-dataset", str(tmp_path / "none"), "--cad", str(tmp_path / "x.ply"),
                                   "--out", str(tmp_path / "out"), "--executor", "spark"])
    assert res.exit_code == 1 and "unknown executor 'spark'" in res.output
    assert not (tmp_path / "out").exists()


LOCAL_BUILD = """
import sys
from typer.testing import CliRunner
from cadalign.cli.main import app
res = CliRunner().invoke(app, sys.argv[1:])
assert res.exit_code == 0, res.output
print("RAY_IMPORTED" if any(m == "ray" or m.startswith("ray.") for m in sys.modules) else "NO_RAY")
"""


def test_local_build_does_not_import_ray(local_build: Path, scale_capture: tuple[Path, Path], tmp_path: Path) -> None:
    """In a fresh interpreter (this test session may have imported Ray): the default executor renders every
    frame without importing Ray, and writes the reference bytes."""
    spec, sim = scale_capture
    out = fresh_out(local_build, tmp_path / "local")
    args = ["build-dataset", str(sim / "frames"), "--cad", str(spec), "--out", str(out), "--preset", "fast",
            "--init", str(local_build / "picks.json")]
    proc = subprocess.run([sys.executable, "-c", LOCAL_BUILD, *args], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().splitlines()[-1] == "NO_RAY"
    assert dataset_bytes(out) == dataset_bytes(local_build)


def test_read_jobs_resolves_paths_defaults_and_names(tmp_path: Path) -> None:
    from cadalign.build.videos import VideoJob, read_jobs

    jobs = write_jobs(tmp_path / "jobs.toml", [{"source": "dives/d1.mp4", "init": "p1.json"},
                                               {"source": "/abs/d2", "name": "second", "cad": "other.ply",
                                                "cad_unit": "mm"}])
    got = read_jobs(jobs, cad=tmp_path / "scene.toml", calib=tmp_path / "cal.json")
    assert got == [VideoJob("d1", tmp_path / "dives" / "d1.mp4", tmp_path / "scene.toml", tmp_path / "p1.json",
                            tmp_path / "cal.json"),
                   VideoJob("second", Path("/abs/d2"), tmp_path / "other.ply", None, tmp_path / "cal.json", None, "mm")]


@pytest.mark.parametrize(("entries", "message"), [
    ([{"source": "a.mp4", "picks": "p.json"}], r"unknown keys \['picks'\]"),
    ([{"name": "x"}], "no 'source'"),
    ([{"source": "x/a.mp4"}, {"source": "y/a.mp4"}], r"same folder \['a'\]"),
    ([], "expected only \\[\\[video\\]\\] entries"),
])
def test_read_jobs_refuses_bad_files(tmp_path: Path, entries: list, message: str) -> None:
    from cadalign.build.videos import read_jobs

    jobs = write_jobs(tmp_path / "jobs.toml", entries)
    with pytest.raises(ConfigError, match=message):
        read_jobs(jobs, cad=tmp_path / "scene.toml")
    with pytest.raises(ConfigError, match="no 'cad' and no --cad"):
        read_jobs(write_jobs(tmp_path / "j2.toml", [{"source": "a.mp4"}]))


def test_local_jobs_build_keeps_going_past_a_failed_video(local_build: Path, scale_capture: tuple[Path, Path],
                                                          tmp_path: Path) -> None:
    """Two videos, one with a missing source: the good one is built (reference bytes), the bad one is
    reported, and the command exits 1; --init belongs in the jobs file."""
    spec, sim = scale_capture
    root = tmp_path / "root"
    fresh_out(local_build, root / "good")
    jobs = write_jobs(tmp_path / "jobs.toml", [
        {"source": str(sim / "frames"), "name": "good", "init": str(local_build / "picks.json")},
        {"source": str(tmp_path / "missing.mp4")}])
    res = CliRunner().invoke(app, jobs_args(jobs, spec, root, "--init", str(local_build / "picks.json")))
    assert res.exit_code == 1 and "--init and --gt belong to one video" in res.output
    res = CliRunner().invoke(app, jobs_args(jobs, spec, root))
    assert res.exit_code == 1, res.output
    assert "1/2 videos built" in " ".join(res.output.split())
    report = read_json(root / "videos_report.json")
    assert report["failed"] == ["missing"] and "input not found" in report["videos"][1]["error"]
    assert report["videos"][0] == {"name": "good", "out": str(root / "good"), "ok": True, "frames": 12, "error": None}
    assert dataset_bytes(root / "good") == dataset_bytes(local_build)

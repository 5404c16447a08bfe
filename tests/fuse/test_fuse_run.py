"""The fusion stage and ``cadalign fuse`` end to end on the tiny simulated scene."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.errors import ConfigError, InputError
from cadalign.fuse.config import FuseConfig
from cadalign.fuse.map_io import load_map, read_ply
from cadalign.fuse.run import REPORT, run
from cadalign.io import read_image, read_json


@pytest.fixture(scope="module")
def fused_dir(fuse_sim: Path, small_cfg: FuseConfig, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return run(small_cfg, fuse_sim, tmp_path_factory.mktemp("fuse") / "map")


def test_run_writes_map_mesh_report_and_views(fused_dir: Path) -> None:
    report = read_json(fused_dir / REPORT)
    assert report["timing"]["frames"] == 6 and report["timing"]["frames_per_second"] > 0
    m = report["metrics"]
    assert m["completeness_within_5cm"] > 0.9 and m["label_accuracy"] > 0.95 and m["accuracy_mean_m"] < 0.02
    vert, faces = read_ply(fused_dir / "mesh.ply")
    assert len(vert) == report["map"]["mesh_vertices"] and faces is not None and faces.max() < len(vert)
    assert set(np.unique(vert["class"])) <= {0, 1, 2, 3}
    img = read_image(fused_dir / "views.png")
    assert img.ndim == 3 and img.shape[0] > 300 and img.std() > 10
    mp, meta = load_map(fused_dir / "map.npz")
    assert len(meta.frame_ids) == 6 and meta.class_names == tuple(report["classes"])


def test_rerun_reuses_and_other_config_is_refused(fused_dir: Path, fuse_sim: Path, small_cfg: FuseConfig) -> None:
    stamp = (fused_dir / REPORT).stat().st_mtime_ns
    assert run(small_cfg, fuse_sim, fused_dir) == fused_dir
    assert (fused_dir / REPORT).stat().st_mtime_ns == stamp
    with pytest.raises(ConfigError, match="another config"):
        run(dataclasses.replace(small_cfg, voxel_m=0.05), fuse_sim, fused_dir)


def test_interrupted_run_continues_from_its_checkpoint(fuse_sim: Path, small_cfg: FuseConfig, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    from cadalign.fuse.tsdf import SemanticTSDF

    real = SemanticTSDF.integrate
    calls = []

    def crash_on_fifth(self, frame):  # noqa: ANN001, ANN202 - test double
        calls.append(1)
        if len(calls) == 5:
            raise KeyboardInterrupt
        return real(self, frame)

    monkeypatch.setattr(SemanticTSDF, "integrate", crash_on_fifth)
    with pytest.raises(KeyboardInterrupt):
        run(small_cfg, fuse_sim, tmp_path / "m", checkpoint_every=2, with_eval=False)
    assert len(load_map(tmp_path / "m" / "map.npz")[1].frame_ids) == 4
    monkeypatch.setattr(SemanticTSDF, "integrate", real)
    run(small_cfg, fuse_sim, tmp_path / "m", checkpoint_every=2, with_eval=False)
    report = read_json(tmp_path / "m" / REPORT)
    assert report["timing"]["frames"] == 2
    assert load_map(tmp_path / "m" / "map.npz")[1].frame_ids == list(range(6))
    # another config with --overwrite, stopped early: the first run's report no longer marks the folder finished
    calls.clear()
    monkeypatch.setattr(SemanticTSDF, "integrate", crash_on_fifth)
    other = dataclasses.replace(small_cfg, voxel_m=small_cfg.voxel_m * 1.5)
    with pytest.raises(KeyboardInterrupt):
        run(other, fuse_sim, tmp_path / "m", checkpoint_every=2, with_eval=False, overwrite=True)
    assert not (tmp_path / "m" / REPORT).exists()


def test_missing_models_and_sources_are_clear_errors(fuse_sim: Path, small_cfg: FuseConfig, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="--labels pred needs a segmentation model: pass --model-seg"):
        run(small_cfg, fuse_sim, tmp_path / "a", labels="pred")
    with pytest.raises(InputError, match="--depth pred needs a depth model: pass --model-depth"):
        run(small_cfg, fuse_sim, tmp_path / "b", depth="pred")
    with pytest.raises(InputError, match="depth_sfm"):
        run(small_cfg, fuse_sim, tmp_path / "c", depth="sfm")
    with pytest.raises(InputError, match="holds no BOP scene"):
        run(small_cfg, tmp_path, tmp_path / "d")
    with pytest.raises(InputError, match="unknown depth source"):
        run(small_cfg, fuse_sim, tmp_path / "e", depth="lidar")


def test_predicted_inputs_plug_in_as_callables(fuse_sim: Path, small_cfg: FuseConfig) -> None:
    """Any ``rgb -> probs`` / ``(rgb, camera) -> depth`` function drives the map (here: the truth, disguised)."""
    from cadalign.fuse.inputs import FrameSource, open_source
    from cadalign.fuse.map_io import new_map
    from cadalign.fuse.semantic import probs_from_labels

    gt = open_source(fuse_sim)
    by_rgb = {gt.scene.rgb(i).tobytes(): i for i in gt.ids}
    seg = lambda rgb: probs_from_labels(gt.label_map(by_rgb[rgb.tobytes()]), gt.n_classes, 0.9)  # noqa: E731
    dep = lambda rgb, cam: gt.scene.depth_m(by_rgb[rgb.tobytes()])  # noqa: E731
    pred = FrameSource(gt.scene, gt.classes, gt.ids[:2], "pred", "pred", 0.9, dep, seg)
    m = new_map(small_cfg, pred.n_classes)
    for frame in pred:
        m.integrate(frame)
    assert len(m.extract_points()) > 1000


def test_bench_fuse(fuse_sim: Path, small_cfg: FuseConfig, tmp_path: Path) -> None:
    from cadalign.bench.fuse_timing import bench_fuse

    r = bench_fuse(fuse_sim, small_cfg, frames=2, warmup=1, out=tmp_path)
    assert r["frames_timed"] == 2 and r["frames_per_second_median"] > 0 and r["image"] == "160x120"
    assert set(r["seconds_by_part"]) == {"tsdf", "labels"} and set(r["baseline"]["ms_by_part"]) == {"tsdf", "labels"}
    assert r["config"]["label_lookup"] == "frustum" and r["baseline_config"]["label_lookup"] == "reference"
    assert r["speedup_wall"] > 0 and r["speedup_cpu"] > 0 and r["cpu_ms_per_frame_median"] > 0
    assert r["load_average_before"] >= 0 and r["cpu_count"] >= 1
    # Open3D's grid alone, timed in the same run: geometry only
    assert r["open3d"]["frames_per_second_median"] > 0 and set(r["open3d"]["ms_by_part"]) == {"tsdf"}
    assert r["fps_vs_open3d"] > 0 and r["fps_vs_open3d_mean"] > 0
    saved = read_json(tmp_path / "bench_fuse.json")
    assert saved["frames_timed"] == 2 and saved["baseline"]["frames_per_second_median"] > 0


def test_time_interleaved_gives_each_config_its_own_map(fuse_sim: Path, small_cfg: FuseConfig) -> None:
    from cadalign.bench.fuse_timing import time_interleaved
    from cadalign.fuse.inputs import open_source

    src = open_source(fuse_sim, max_frames=3)
    frames = [src.frame(i) for i in src.ids]
    coarse = dataclasses.replace(small_cfg, voxel_m=0.06)
    timings, maps = time_interleaved(frames, src.n_classes, {"a": small_cfg, "b": coarse}, warmup=1)
    assert [len(t.wall_s) for t in timings.values()] == [2, 2]
    assert maps["a"].frames_integrated == maps["b"].frames_integrated == 3
    assert maps["a"].n_blocks != maps["b"].n_blocks  # two separate maps, each with its own config


def test_cli_help() -> None:
    result = CliRunner().invoke(app, ["fuse", "--help"])
    assert result.exit_code == 0 and "--method" in result.output and "--model-seg" in result.output


def test_cli_end_to_end(fuse_sim: Path, tmp_path: Path) -> None:
    out = tmp_path / "cli_map"
    args = ["fuse", str(fuse_sim), "--out", str(out), "--voxel", "0.04", "--method", "surfel", "--ids", "1:4",
            "--no-eval"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    report = read_json(out / REPORT)
    assert report["method"] == "surfel" and report["timing"]["frames"] == 3 and report["metrics"] is None
    assert load_map(out / "map.npz")[1].frame_ids == [1, 2, 3]
    bad = CliRunner().invoke(app, ["fuse", str(fuse_sim), "--out", str(tmp_path / "x"), "--method", "octree"])
    assert bad.exit_code == 1 and "method" in bad.output
    bad = CliRunner().invoke(app, ["fuse", str(fuse_sim), "--out", str(tmp_path / "y"), "--ids", "3-5"])
    assert bad.exit_code == 2 and "A:B" in bad.output


def test_bench_fuse_sweep_measures_new_and_old_in_one_run(fuse_sim: Path) -> None:
    from cadalign.bench.sweeps.fuse import fuse_measure
    from cadalign.fuse.inputs import open_source

    src = open_source(fuse_sim, max_frames=2)
    shared = (src, [src.frame(i) for i in src.ids])
    met = fuse_measure(shared, {"voxel_m": 0.06, "preset": "realtime"}, seed=0)
    assert met["ms_per_frame"] > 0 and met["old_ms_per_frame"] > 0 and met["speedup_vs_old"] > 0
    assert met["ms_tsdf"] > 0 and met["ms_labels"] > 0 and met["cpu_ms_per_frame"] > 0
    assert met["speedup_cpu_vs_old"] > 0 and met["load_average"] >= 0
    assert 0 < met["chamfer_m"] < 0.1 and met["label_accuracy"] > 0.5
    assert met["open3d_ms_per_frame"] > 0 and met["fps_vs_open3d"] > 0


@pytest.mark.parametrize("size", ["tiny", "full"])
def test_bench_fuse_sweep_has_open3d_alone_as_its_baseline(size: str, tmp_path: Path) -> None:
    from cadalign.bench.data import SIZES, BenchData
    from cadalign.bench.registry import BenchConfig
    from cadalign.bench.sweeps.fuse import FUSE_OPEN3D, fuse_sweep

    sweep = fuse_sweep(BenchData(tmp_path, SIZES[size]), BenchConfig(size=size))  # nothing runs yet
    base = [p for p in sweep.points if p.name == sweep.baseline]
    assert len(base) == 1 and FUSE_OPEN3D in base[0].name and base[0].knobs["open3d_alone"]
    assert base[0].knobs["voxel_m"] == min(p.knobs["voxel_m"] for p in sweep.points)


def test_bench_fuse_open3d_alone_setting(fuse_sim: Path) -> None:
    from cadalign.bench.sweeps.fuse import fuse_measure
    from cadalign.fuse.inputs import open_source

    src = open_source(fuse_sim, max_frames=2)
    shared = (src, [src.frame(i) for i in src.ids])
    met = fuse_measure(shared, {"voxel_m": 0.06, "open3d_alone": True}, seed=0)
    assert met["ms_per_frame"] > 0 and met["ms_tsdf"] > 0 and "ms_labels" not in met
    # Open3D's own mesh of the same frames lies on the CAD like ours; not on the accuracy axis (never recommended)
    assert 0 < met["open3d_chamfer_m"] < 0.1 and "chamfer_m" not in met


def test_views_build_one_raycasting_scene_and_cast_each_view_once(fused_dir: Path, monkeypatch) -> None:
    """The picture's two rows are the same views coloured two ways: one BVH, one cast per view, and the same pixels
    as rendering each tile on its own with ``render_view``."""
    from cadalign.fuse import views
    from cadalign.fuse.base import LabelledGeometry

    vert, faces = read_ply(fused_dir / "mesh.ply")
    pts = np.stack([vert["x"], vert["y"], vert["z"]], 1)
    labels = vert["class"].astype(np.int64)
    mesh = LabelledGeometry(pts, np.zeros_like(pts, dtype=np.float32),
                            np.stack([vert["red"], vert["green"], vert["blue"]], 1), labels,
                            np.ones((len(pts), 1), np.float32), faces.astype(np.int64))
    calls = {"scene": 0, "cast": 0}
    for name in calls:
        real = getattr(views, f"_{name}")

        def counted(*a, _real=real, _name=name, **k):
            calls[_name] += 1
            return _real(*a, **k)

        monkeypatch.setattr(views, f"_{name}", counted)
    size = (64, 48)
    img = read_image(views.render_views(mesh, fused_dir / "views_again.png", ["bg", "a", "b"], size=size))
    assert calls == {"scene": 1, "cast": 3}
    fg = pts[labels != 0]
    lo, hi = np.percentile(fg if len(fg) >= 100 else pts, [1, 99], axis=0)
    target, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)), 1e-3)
    for k in range(3):
        a = 2 * np.pi * k / 3 + np.pi / 6
        eye = target + 1.1 * radius * np.array([np.cos(a), np.sin(a), 0.55])
        for row, by_class in enumerate((True, False)):
            tile = views.render_view(mesh, eye, target, size, by_class=by_class)
            np.testing.assert_array_equal(img[28 + 48 * row: 28 + 48 * (row + 1), 64 * k: 64 * (k + 1)], tile)


def test_bop_scene_parses_each_frame_once(fuse_sim: Path, monkeypatch) -> None:
    """Every mask/depth/rgb read checks its size against its frame: the frame's JSON is parsed once, not per read."""
    from cadalign.formats.bop import BopScene

    scene = BopScene(fuse_sim / "gt" / "sim" / "000000")
    parsed = []
    real = scene._parse_frame
    monkeypatch.setattr(scene, "_parse_frame", lambda i: parsed.append(i) or real(i))
    im_id = scene.ids[0]
    frame = scene.frame(im_id)
    assert len(frame.instances) >= 2
    for g in range(len(frame.instances)):
        scene.mask(im_id, g)
    scene.depth_m(im_id)
    assert parsed == [im_id] and scene.frame(im_id) is frame


def test_bench_fuse_labels_command_times_a_users_scene(fuse_sim: Path, tmp_path: Path) -> None:
    """`cadalign bench fuse-labels SCENE`: fusion with labels against Open3D's grid alone on a given BOP scene."""
    from typer.testing import CliRunner

    from cadalign.cli.main import app

    res = CliRunner().invoke(app, ["bench", "fuse-labels", str(fuse_sim), "--frames", "2", "--voxel-m", "0.05",
                                   "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    saved = read_json(tmp_path / "bench_fuse.json")
    assert saved["frames_timed"] == 2 and saved["voxel_m"] == 0.05 and saved["fps_vs_open3d"] > 0
    assert "Open3D alone" in res.output
    bad = CliRunner().invoke(app, ["bench", "fuse-labels", str(tmp_path / "nowhere"), "--out", str(tmp_path)])
    assert bad.exit_code != 0 and "Traceback" not in bad.output

"""``cadalign emulate``: help, tiny end-to-end runs of every sensor, reuse, refusal and readable errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.geometry import intrinsics

runner = CliRunner()


@pytest.mark.parametrize("cmd", [[], ["lidar"], ["sonar"], ["view"], ["mesh"]])
def test_help(cmd: list[str]) -> None:
    res = runner.invoke(app, ["emulate", *cmd, "--help"])
    assert res.exit_code == 0, res.output
    assert "Usage" in res.output


def test_lidar_end_to_end_reuse_and_refusal(tiny_scene_path, tmp_path) -> None:
    cfg = tmp_path / "small.toml"
    cfg.write_text("horizontal_res_deg = 4.0\nchannels = 8\n")
    out = tmp_path / "lidar"
    args = ["emulate", "lidar", str(tiny_scene_path), "--out", str(out), "--preset", "vlp16", "--config", str(cfg),
            "--pose", "2.5,-2.0,1.0"]
    res = runner.invoke(app, args)
    assert res.exit_code == 0, res.output
    for name in ("scan.npz", "scan.ply", "lidar_class.png", "emulate.json", "cadalign_stage.json"):
        assert (out / name).is_file(), name
    summary = json.loads((out / "emulate.json").read_text())
    assert summary["rays"] == 8 * 90 and 0 < summary["returns"] <= summary["rays"]
    with np.load(out / "scan.npz") as z:
        assert np.allclose(np.linalg.norm(z["xyz_world"] - [2.5, -2.0, 1.0], axis=1), z["range_m"], atol=1e-9)
    mtime = (out / "scan.npz").stat().st_mtime_ns
    assert runner.invoke(app, args).exit_code == 0 and (out / "scan.npz").stat().st_mtime_ns == mtime  # reused
    res = runner.invoke(app, args[:-2] + ["--pose", "2.5,-2.0,1.5"])
    assert res.exit_code == 1 and "--overwrite" in res.output


def test_sonar_and_view_with_default_pose_and_look_at(tiny_scene_path, tmp_path) -> None:
    res = runner.invoke(app, ["emulate", "sonar", str(tiny_scene_path), "--out", str(tmp_path / "s"), "--preset",
                              "fast", "--look-at", "0,0,0.3"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "s" / "sonar.png").is_file() and (tmp_path / "s" / "sonar_polar.png").is_file()
    with np.load(tmp_path / "s" / "sonar.npz") as z:
        assert z["intensity"].shape == (256, 128) and (z["class_id"] >= 1).any()  # the structure is seen
    res = runner.invoke(app, ["emulate", "view", str(tiny_scene_path), "--out", str(tmp_path / "v"), "--preset",
                              "small", "--engine", "torch"])
    assert res.exit_code == 0, res.output
    with np.load(tmp_path / "v" / "view.npz") as z:
        assert z["rgb"].shape == (120, 160, 3) and (z["class_id"] > 0).any() and (z["depth_m"] > 0).any()


def test_mesh_from_an_npz_image_and_view_of_the_written_mesh(tmp_path) -> None:
    H, W = 24, 32
    depth = np.full((H, W), 2.0)
    pane = np.zeros((H, W), bool)
    pane[6:18, 8:24] = True
    np.savez(tmp_path / "img.npz", rgb=np.full((H, W, 3), 90, np.uint8), depth_m=depth,
             K=intrinsics(30.0, 30.0, 16.0, 12.0), class_id=np.ones((H, W), np.int32), pane_mask=pane)
    res = runner.invoke(app, ["emulate", "mesh", str(tmp_path / "img.npz"), "--out", str(tmp_path / "m")])
    assert res.exit_code == 0, res.output
    ply = tmp_path / "m" / "layered_mesh.ply"
    assert ply.is_file() and (tmp_path / "m" / "preview_rgb.png").is_file()
    assert json.loads((tmp_path / "m" / "emulate.json").read_text())["panes"] == 1
    res = runner.invoke(app, ["emulate", "view", str(ply), "--out", str(tmp_path / "v"), "--preset", "small",
                              "--pose", "0,0,0"])
    assert res.exit_code == 0, res.output


def test_readable_errors(tiny_scene_path, tmp_path) -> None:
    res = runner.invoke(app, ["emulate", "lidar", str(tiny_scene_path), "--out", str(tmp_path / "a"), "--pose", "1,2"])
    assert res.exit_code == 1 and "x,y,z" in res.output
    res = runner.invoke(app, ["emulate", "mesh", str(tiny_scene_path), "--out", str(tmp_path / "b")])
    assert res.exit_code == 1 and "from one image" in res.output
    res = runner.invoke(app, ["emulate", "lidar", str(tiny_scene_path), "--out", str(tmp_path / "c"), "--preset", "x"])
    assert res.exit_code == 1 and "allowed presets" in res.output
    (tmp_path / "m.ply").write_text("not a ply")
    res = runner.invoke(app, ["emulate", "view", str(tmp_path / "m.ply"), "--out", str(tmp_path / "d")])
    assert res.exit_code == 1 and "no default pose" in res.output


def test_bench_emulate_on_the_tiny_scene(tiny_scene_path, tmp_path) -> None:
    from cadalign.bench.emulate import bench_emulate

    r = bench_emulate(tiny_scene_path, tmp_path, rings=16, azimuths=128, torch_rays=500, agree_rays=2000, rounds=1,
                      poses=2, torch_threads=(1,))
    assert r["rays"] == 16 * 128 and r["bvh_cast_rays_per_s"] > 0 and r["torch_by_threads"]["1"]["rays_per_s"] > 0
    assert r["agreement"]["agree_fraction"] >= 0.999 and r["agreement"]["class_agree_fraction"] >= 0.999
    assert (tmp_path / "bench_emulate.json").is_file()


@pytest.mark.parametrize("name", ["box.obj", "box.stl", "box_ascii.ply", "box.off"])
def test_lidar_reads_every_mesh_format(name: str, tmp_path) -> None:
    """OBJ, STL, OFF (through :func:`cadalign.cad.load.load_cad`) and an ASCII PLY all give the same scan of a
    2 m box around the sensor (ASCII PLY once crashed on its dict of properties)."""
    import trimesh

    mesh = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    path = tmp_path / name
    mesh.export(path, encoding="ascii") if name.endswith(".ply") else mesh.export(path)
    cfg = tmp_path / "small.toml"
    cfg.write_text("horizontal_res_deg = 10.0\nchannels = 8\nrange_noise_m = 0.0\ndropout = 0.0\n")
    out = tmp_path / "out"
    res = runner.invoke(app, ["emulate", "lidar", str(path), "--out", str(out), "--preset", "vlp16", "--config",
                              str(cfg), "--pose", "0,0,0", "--unit", "m"])
    assert res.exit_code == 0, res.output
    with np.load(out / "scan.npz") as z:
        r = z["range_m"]
        assert len(r) == 8 * 36 and np.all((r >= 1.0 - 1e-9) & (r <= np.sqrt(3) + 1e-9))  # inside the box: all hit


def test_mesh_unit_scales_and_is_refused_for_a_scene(tiny_scene_path, tmp_path) -> None:
    import trimesh

    from cadalign.emulate.sources import load_source

    path = tmp_path / "box.stl"
    trimesh.creation.box(extents=(2000.0, 2000.0, 2000.0)).export(path)
    assert np.allclose(np.ptp(load_source(path, unit="mm").vertices_m, axis=0), 2.0)
    res = runner.invoke(app, ["emulate", "lidar", str(tiny_scene_path), "--out", str(tmp_path / "a"), "--unit", "mm"])
    assert res.exit_code == 1 and "unit applies to a mesh file" in " ".join(res.output.split())

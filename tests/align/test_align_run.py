"""``run``: align.json + align.png written atomically, reuse, config refusal, failures write nothing."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from cadalign.align import ALIGN_JSON, ALIGN_PNG, PRESETS, AlignmentGateError, load_points, read_sim3, run
from cadalign.align.run import read_picks
from cadalign.errors import ConfigError, InputError
from cadalign.io import MANIFEST_NAME

FAST = PRESETS["fast"]


@pytest.fixture(scope="module")
def written(small_cloud, parts, tmp_path_factory):
    """One finished run (prior path: the I/O is under test here, not the registration)."""
    out = tmp_path_factory.mktemp("align")
    np.save(out.parent / "points.npy", small_cloud.points_sfm)
    path = run(FAST, out.parent / "points.npy", parts, out, prior=small_cloud.cad_from_sfm)
    return out, path


def test_writes_align_json_and_png(written, small_cloud):
    out, path = written
    assert path == out / ALIGN_JSON
    assert (out / ALIGN_PNG).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in out.iterdir()) == sorted([ALIGN_JSON, ALIGN_PNG, MANIFEST_NAME])  # no temp files
    data = json.loads(path.read_text())
    assert set(data) >= {"version", "cad_from_sfm", "sfm_from_cad", "coarse", "metrics", "gates", "seconds",
                         "history", "config", "inputs"}
    T = data["cad_from_sfm"]
    M = np.array(T["matrix"])
    assert np.allclose(M[:3, :3], T["s"] * np.array(T["R"])) and np.allclose(M[:3, 3], T["t"])
    assert np.allclose(M @ np.array(data["sfm_from_cad"]["matrix"]), np.eye(4), atol=1e-9)
    assert all(g["passed"] for g in data["gates"])
    assert data["coarse"]["method"] == "prior"
    assert data["config"]["icp"]["trim_keep"] == FAST.icp.trim_keep
    assert data["inputs"]["points_sfm"]["n"] == len(small_cloud.points_sfm)
    assert len(data["inputs"]["cad"]) == 5


def test_read_sim3_round_trips(written, small_cloud):
    _, path = written
    T = read_sim3(path)
    assert T.s == pytest.approx(small_cloud.cad_from_sfm.s, rel=1e-3)


def test_rerun_reuses_and_another_config_is_refused(written, small_cloud, parts):
    out, path = written
    points = out.parent / "points.npy"
    before = path.stat().st_mtime_ns
    assert run(FAST, points, parts, out, prior=small_cloud.cad_from_sfm) == path
    assert path.stat().st_mtime_ns == before
    other = replace(FAST, seed=1)
    with pytest.raises(ConfigError, match="another config"):
        run(other, points, parts, out, prior=small_cloud.cad_from_sfm)


def test_overwrite_replaces(small_cloud, parts, tmp_path):
    run(FAST, small_cloud.points_sfm, parts, tmp_path, prior=small_cloud.cad_from_sfm)
    other = replace(FAST, seed=1, figure=False)
    path = run(other, small_cloud.points_sfm, parts, tmp_path, prior=small_cloud.cad_from_sfm, overwrite=True)
    assert json.loads(path.read_text())["config"]["seed"] == 1
    assert not (tmp_path / ALIGN_PNG).exists()  # the old figure went with the old result


def test_failure_writes_nothing_and_frees_the_directory(small_cloud, parts, tmp_path):
    from cadalign.types import Rigid3

    wrong_unit = [(m.scaled(1000.0), Rigid3(T.R, T.t * 1000.0)) for m, T in parts]
    with pytest.raises(AlignmentGateError):
        run(FAST, small_cloud.points_sfm, wrong_unit, tmp_path, prior=small_cloud.cad_from_sfm)
    assert list(tmp_path.iterdir()) == []
    # fixed input, same directory, no --overwrite needed
    assert run(FAST, small_cloud.points_sfm, parts, tmp_path, prior=small_cloud.cad_from_sfm).is_file()


def test_picks_file_and_prior_file(small_cloud, parts, tmp_path, written):
    cad = np.array([[4.35, 4.85, 6.0], [-4.35, -4.85, 6.0], [4.35, -4.85, 0.0], [-2.5, 0.0, 3.6]])
    sfm = small_cloud.cad_from_sfm.inverse().apply(cad)
    picks = tmp_path / "picks.json"
    pairs = [{"sfm": a.tolist(), "cad_m": b.tolist()} for a, b in zip(sfm, cad, strict=True)]
    picks.write_text(json.dumps({"pairs": pairs}))
    assert len(read_picks(picks).names) == 4
    path = run(FAST, small_cloud.points_sfm, parts, tmp_path / "a", picks=picks)
    assert json.loads(path.read_text())["coarse"]["method"] == "picks"
    prior_path = written[1]  # a previous align.json is a valid prior
    path = run(FAST, small_cloud.points_sfm, parts, tmp_path / "b", prior=prior_path)
    assert json.loads(path.read_text())["coarse"]["method"] == "prior"


def test_load_points_formats(tmp_path, small_cloud):
    import open3d as o3d

    pts = small_cloud.points_sfm[:500]
    np.save(tmp_path / "p.npy", pts)
    o3d.io.write_point_cloud(str(tmp_path / "p.ply"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts)))
    assert np.array_equal(load_points(tmp_path / "p.npy"), pts)
    assert np.allclose(load_points(tmp_path / "p.ply"), pts)
    assert load_points(pts) is pts


def test_load_points_from_a_colmap_model(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    rec = pycolmap.Reconstruction()
    xyz = np.random.default_rng(0).normal(size=(20, 3))
    for p in xyz:
        rec.add_point3D(p, pycolmap.Track(), np.zeros(3, np.uint8))
    rec.write(str(tmp_path))
    got = load_points(tmp_path)
    assert np.allclose(np.sort(got, axis=0), np.sort(xyz, axis=0))


@pytest.mark.parametrize(
    ("name", "content", "match"),
    [
        ("missing.npy", None, "not found"),
        ("p.txt", "1 2 3", "unsupported point file"),
        ("p.npy", np.zeros((4, 2)), "expected N x 3"),
        ("empty", "dir", "not a COLMAP sparse model"),
    ],
)
def test_load_points_errors(tmp_path, name, content, match):
    path = tmp_path / name
    if isinstance(content, str) and content == "dir":
        path.mkdir()
    elif isinstance(content, str):
        path.write_text(content)
    elif content is not None:
        np.save(path, content)
    with pytest.raises(InputError, match=match):
        load_points(path)


def test_prior_file_errors(tmp_path):
    bad = tmp_path / "prior.json"
    bad.write_text(json.dumps({"matrix": np.diag([1.0, 2.0, 3.0, 1.0]).tolist()}))
    with pytest.raises(InputError, match="not a 4x4 similarity"):
        read_sim3(bad)
    bad.write_text(json.dumps({"pose": 1}))
    with pytest.raises(InputError, match="'matrix'"):
        read_sim3(bad)


def test_cad_given_as_files_with_poses(small_cloud, parts, tmp_path):
    """Mesh files are loaded with load_cad (unit detected) and paired with their world poses."""
    import trimesh

    cad = []
    for i, (model, pose) in enumerate(parts):
        path = tmp_path / f"part_{i}.ply"
        trimesh.Trimesh(np.asarray(model.vertices_m), np.asarray(model.faces), process=False).export(path)
        cad.append((path, pose))
    out = run(FAST, small_cloud.points_sfm, cad, tmp_path / "out", prior=small_cloud.cad_from_sfm)
    data = json.loads(out.read_text())
    assert [c["unit"] for c in data["inputs"]["cad"]] == ["m"] * len(parts)
    assert data["inputs"]["cad"][0]["source"].endswith("part_0.ply")

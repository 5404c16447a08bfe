"""``cadalign align`` end to end: a scene spec as CAD, SfM-like points with a known Sim3, and picks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.geometry import geodesic_angle
from cadalign.io import read_json, write_json
from cadalign.sim.structure import load_structure
from cadalign.testing.tiny_scene import write_tiny_scene
from cadalign.types import Sim3


def test_align_cli_recovers_a_known_sim3_and_refuses_a_wrong_unit(tmp_path: Path, shared_data: Path) -> None:
    spec = write_tiny_scene(tmp_path / "tiny.toml", effects=[], frames=2)
    structure = load_structure(spec)
    rng = np.random.default_rng(3)
    import trimesh

    meshes = [trimesh.Trimesh(o.T_world_from_obj.apply(structure.models[o.obj_id].vertices_m),
                              structure.models[o.obj_id].faces) for o in structure.objects]
    surf = np.concatenate([trimesh.sample.sample_surface(m, 1500, seed=1)[0] for m in meshes])
    seabed = np.c_[rng.uniform(-3, 3, (1500, 2)), rng.normal(0, 0.01, 1500)]
    cloud_world = np.concatenate([surf + rng.normal(0, 0.005, surf.shape), seabed])
    true = Sim3(0.25, Rotation.from_rotvec([0.3, -1.2, 0.5]).as_matrix(), np.array([3.0, -1.0, 7.0]))
    sfm = true.inverse().apply(cloud_world)
    np.save(tmp_path / "points.npy", sfm)
    cad_pts = np.array([[0.6, 0.4, 0.9], [-0.6, -0.4, 0.9], [0.6, -0.4, 0.3], [-0.6, 0.4, 0.3]])
    write_json(tmp_path / "picks.json", {"pairs": [{"sfm": s.tolist(), "cad_m": c.tolist()} for s, c in
                                                   zip(true.inverse().apply(cad_pts), cad_pts, strict=True)]})
    runner = CliRunner()
    res = runner.invoke(app, ["align", str(tmp_path / "points.npy"), "--cad", str(spec), "--out",
                              str(tmp_path / "al"), "--preset", "fast", "--init", str(tmp_path / "picks.json")])
    assert res.exit_code == 0, res.output
    rec = read_json(tmp_path / "al" / "align.json")
    M = np.array(rec["cad_from_sfm"]["matrix"])
    s = np.cbrt(np.linalg.det(M[:3, :3]))
    assert abs(s / true.s - 1) < 0.005
    assert np.degrees(geodesic_angle(M[:3, :3] / s, true.R)) < 0.3
    assert np.abs(M[:3, :3] @ sfm[:100].T + M[:3, 3:] - cloud_world[:100].T).max() < 0.05
    # the same points against the hot stab alone read in mm: the gate fails with a unit hint, exit 1
    hot_stab = shared_data / "uuv_subsea_cad" / "hot_stab" / "meshes" / "HotStab.dae"
    bad = runner.invoke(app, ["align", str(tmp_path / "points.npy"), "--cad", str(hot_stab), "--out",
                              str(tmp_path / "bad"), "--preset", "fast", "--cad-unit", "mm"])
    assert bad.exit_code == 1 and "unit" in bad.output.lower()
    assert not (tmp_path / "bad" / "align.json").exists()

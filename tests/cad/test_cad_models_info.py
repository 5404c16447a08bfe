"""BOP models_info.json entries and PLY export, in millimetres."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from cad_testdata import unit_cube_mesh

from cadalign.cad import CadModel, Symmetry, load_cad, models_info_entry, write_model_ply_mm, write_models_info
from cadalign.errors import InputError


def test_unit_cube_entry_in_mm(unit_cube: CadModel) -> None:
    e = models_info_entry(unit_cube)
    assert e["diameter"] == pytest.approx(np.sqrt(3) * 1000.0, abs=1e-6)
    assert [e["min_x"], e["min_y"], e["min_z"]] == [0.0, 0.0, 0.0]
    assert [e["size_x"], e["size_y"], e["size_z"]] == [1000.0, 1000.0, 1000.0]
    assert "symmetries_discrete" not in e and "symmetries_continuous" not in e


def test_symmetries_in_mm() -> None:
    v, f = unit_cube_mesh()
    v = v * 0.1 - 0.05  # a 100 mm cube centred at the origin
    rot_x = Symmetry.cyclic((1, 0, 0), 2, offset_m=(0.0, 0.01, 0.0))
    m = CadModel("c", v, f, symmetry=rot_x)
    e = models_info_entry(m)
    assert e["min_x"] == pytest.approx(-50.0) and e["size_z"] == pytest.approx(100.0)
    (T,) = e["symmetries_discrete"]
    T = np.array(T).reshape(4, 4)
    np.testing.assert_allclose(T[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-9)
    np.testing.assert_allclose(T[:3, 3], [0.0, 20.0, 0.0], atol=1e-9)  # offset - R offset, in mm
    cyl = CadModel("c", v, f, symmetry=Symmetry.continuous((0, 0, 2), (0.001, 0.002, 0.0)))
    assert models_info_entry(cyl)["symmetries_continuous"] == [{"axis": [0.0, 0.0, 1.0], "offset": [1.0, 2.0, 0.0]}]


def test_write_models_info_atomic(tmp_path: Path, unit_cube: CadModel, uuv_cad_dir: Path) -> None:
    valve = load_cad(uuv_cad_dir / "rov_bop_panel/meshes/Valve.dae", symmetry="continuous_z")
    out = write_models_info({2: valve, 1: unit_cube}, tmp_path / "models" / "models_info.json")
    info = json.loads(out.read_text())
    assert list(info) == ["1", "2"]
    assert info["2"]["size_x"] == pytest.approx(valve.extent[0] * 1000.0)
    assert 140.0 < info["2"]["diameter"] < 150.0  # the valve is ~145 mm across
    assert info["2"]["symmetries_continuous"][0]["axis"] == [0.0, 0.0, 1.0]
    assert [p.name for p in out.parent.iterdir()] == ["models_info.json"]  # no temp file left behind
    with pytest.raises(InputError, match="ids must be integers >= 1"):
        write_models_info({0: unit_cube}, tmp_path / "bad.json")
    assert not (tmp_path / "bad.json").exists()


def test_write_model_ply_mm_round_trip(tmp_path: Path, uuv_cad_dir: Path) -> None:
    valve = load_cad(uuv_cad_dir / "rov_bop_panel/meshes/Valve.dae")
    path = write_model_ply_mm(valve, tmp_path / "obj_000001.ply")
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "binary_little_endian" in header and "property float nx" in header and "property uchar red" in header
    assert "property list uchar int vertex_indices" in header
    back = trimesh.load(path, process=False)
    np.testing.assert_allclose(back.vertices, valve.vertices_m * 1000.0, rtol=1e-6, atol=1e-3)
    np.testing.assert_array_equal(back.faces, valve.faces)
    np.testing.assert_array_equal(back.visual.vertex_colors[:, :3], valve.vertex_colors[:, :3])
    again = load_cad(path)  # and cadalign reads it back as millimetres
    assert again.unit == "mm"
    np.testing.assert_allclose(again.extent, valve.extent, rtol=1e-6)


def test_write_model_ply_without_colors(tmp_path: Path, unit_cube: CadModel) -> None:
    path = write_model_ply_mm(unit_cube, tmp_path / "obj_000002.ply")
    assert b"red" not in path.read_bytes().split(b"end_header")[0]
    back = trimesh.load(path, process=False)
    assert back.volume == pytest.approx(1e9, rel=1e-6)


@pytest.mark.parametrize("sym", [Symmetry.none(), Symmetry.cyclic((1, 0, 0), 2, offset_m=(0.0, 0.01, 0.0)),
                                 Symmetry.continuous((0, 0, 1), (0.001, 0.002, 0.0))])
def test_symmetry_round_trips_through_models_info(sym: Symmetry) -> None:
    from cadalign.cad.models_info import symmetry_from_entry

    v, f = unit_cube_mesh()
    back = symmetry_from_entry(models_info_entry(CadModel("c", v * 0.1, f, symmetry=sym)))
    assert back.kind == sym.kind
    for a, b in zip(back.discretize(8), sym.discretize(8), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-9)

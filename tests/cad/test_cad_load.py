"""load_cad on the real UUV Simulator meshes, unit handling, formats and input errors."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import trimesh
from cad_testdata import UUV_DAE, unit_cube_mesh

from cadalign.cad import CadModel, Symmetry, check_unit, detect_unit, load_cad, read_cad_parts
from cadalign.errors import InputError, UnitError

# Largest extent (m) of each UUV mesh, measured once; the valves are 0.05-0.6 m class parts.
EXPECTED_LARGEST_M = {
    "rov_bop_panel/meshes/BOP_Panel.dae": 0.80,
    "rov_bop_panel/meshes/Valve.dae": 0.145,
    "rov_bop_panel/meshes/SmallValve.dae": 0.075,
    "hot_stab/meshes/HotStab.dae": 0.515,
    "torque_tool/meshes/TorqueTool.dae": 0.2555,
    "t_bar_fork_tool/meshes/TBarForkTool.dae": 0.28,
    "bop_panel/meshes/Valve.dae": 0.0955,
}


@pytest.mark.parametrize("rel", UUV_DAE)
def test_uuv_dae_loads_in_metres(uuv_cad_dir: Path, rel: str) -> None:
    model = load_cad(uuv_cad_dir / rel)
    print(f"{rel}: unit={model.unit} V={len(model.vertices_m)} F={len(model.faces)} parts={model.n_parts} "
          f"extent={np.round(model.extent, 4).tolist()} m diameter={model.diameter_m:.4f} m")
    assert len(model.faces) > 0
    assert model.unit == "m"
    assert model.source == uuv_cad_dir / rel
    assert model.name == Path(rel).stem
    assert 0.05 < model.extent.max() < 1.0
    assert model.extent.max() == pytest.approx(EXPECTED_LARGEST_M[rel], abs=1e-3)
    assert model.extent.max() <= model.diameter_m <= np.linalg.norm(model.extent) + 1e-12
    assert model.part_labels.shape == (len(model.faces),)
    assert set(np.unique(model.part_labels)) == set(range(model.n_parts))
    assert model.vertex_colors is not None and model.vertex_colors.shape == (len(model.vertices_m), 4)
    tm = model.to_trimesh()
    assert tm.visual.kind == "vertex" and len(tm.faces) == len(model.faces)


def test_multi_node_dae_keeps_parts_and_node_transforms(uuv_cad_dir: Path) -> None:
    path = uuv_cad_dir / "hot_stab/meshes/HotStab.dae"
    parts = read_cad_parts(path)
    model = load_cad(path)
    assert model.n_parts == len(parts.part_names) == 8
    assert model.part_names == parts.part_names
    scene = trimesh.load_scene(path, process=False)
    flat = scene.to_geometry()  # trimesh's own flattening with node transforms
    np.testing.assert_allclose(model.bbox_min, flat.bounds[0], atol=1e-9)
    np.testing.assert_allclose(model.bbox_max, flat.bounds[1], atol=1e-9)
    # cleaning dropped no face here, so face counts per part are those of the file's nodes
    for i, node in enumerate(parts.part_names):
        _, geom = scene.graph[node]
        assert len(model.part_faces(i)) == len(scene.geometry[geom].faces)


def test_mm_file_is_detected_with_warning(uuv_cad_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    valve_m = load_cad(uuv_cad_dir / "rov_bop_panel/meshes/Valve.dae")
    mesh = valve_m.to_trimesh()
    mesh.apply_scale(1000.0)
    ply = tmp_path / "valve_mm.ply"
    mesh.export(ply)
    with caplog.at_level(logging.WARNING, logger="cadalign.cad"):
        valve = load_cad(ply)
    assert valve.unit == "mm"
    np.testing.assert_allclose(valve.extent, valve_m.extent, rtol=1e-6)
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert warnings, "the mm assumption must be logged as a warning"
    text = warnings[0].getMessage()
    assert "valve_mm.ply" in text and "millimetres" in text and "unit=" in text


def test_explicit_unit_is_applied_and_recorded(uuv_cad_dir: Path) -> None:
    path = uuv_cad_dir / "rov_bop_panel/meshes/Valve.dae"
    ref = load_cad(path)
    for unit, factor in (("cm", 0.01), ("mm", 0.001), ("in", 0.0254)):
        m = load_cad(path, unit, clean=False)
        assert m.unit == unit
        np.testing.assert_allclose(m.extent, ref.extent * factor, rtol=1e-9)


def test_check_unit_catches_mm_file_loaded_as_metres(tmp_path: Path) -> None:
    valve = trimesh.creation.cylinder(radius=300.0, height=200.0)  # a 600 mm valve, numbers in mm
    path = tmp_path / "big_valve.stl"
    valve.export(path)
    model = load_cad(path, unit="m", class_name="valve")
    with pytest.raises(UnitError, match=r"CAD 'big_valve.stl' is 600(\.0)? m across; a valve is expected") as err:
        check_unit(model, expected_size_m=(0.1, 2.0))
    assert "Pass unit='mm'" in str(err.value)
    ok = load_cad(path, unit="mm", class_name="valve")
    assert check_unit(ok, (0.1, 2.0)) == pytest.approx(0.6)


def test_check_unit_without_fitting_unit_says_so(unit_cube: CadModel) -> None:
    with pytest.raises(UnitError, match="no unit fits"):
        check_unit(unit_cube, (1e5, 2e5))
    with pytest.raises(UnitError, match="expected_size_m"):
        check_unit(unit_cube, (2.0, 1.0))


def test_detect_unit_rule(caplog: pytest.LogCaptureFixture) -> None:
    assert detect_unit(0.6, "a.ply") == "m"
    assert detect_unit(50.0, "a.ply") == "m"
    with caplog.at_level(logging.WARNING):
        assert detect_unit(600.0, "a.ply") == "mm"
        assert detect_unit(0.001, "tiny.ply") == "m"
    assert any("tiny.ply" in r.getMessage() for r in caplog.records)
    assert detect_unit(600.0, "a.dae", declared="mm") == "mm"
    assert detect_unit(24.0, "a.dae", declared="in") == "in"
    assert detect_unit(600.0, "a.dae", declared="m") == "mm"  # declared metres are implausible here
    with pytest.raises(UnitError, match="huge.ply"):
        detect_unit(60_000.0, "huge.ply")


def test_absurd_size_raises_unit_error(tmp_path: Path) -> None:
    path = tmp_path / "huge.stl"
    trimesh.creation.box(extents=(1e6, 1.0, 1.0)).export(path)
    with pytest.raises(UnitError, match="huge.stl"):
        load_cad(path)


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "glb", "off", "dae"])
def test_formats_round_trip(tmp_path: Path, ext: str) -> None:
    v, f = unit_cube_mesh()
    path = tmp_path / f"cube.{ext}"
    trimesh.Trimesh(v * 0.5, f, process=False).export(path)
    model = load_cad(path, name="cube", class_name="box", symmetry="discrete_z4")
    assert len(model.faces) == 12 and len(model.vertices_m) == 8
    np.testing.assert_allclose(model.extent, [0.5, 0.5, 0.5], atol=1e-6)
    assert model.diameter_m == pytest.approx(0.5 * np.sqrt(3), abs=1e-6)
    assert model.to_trimesh().volume == pytest.approx(0.125, abs=1e-6)  # winding kept outward
    assert (model.name, model.class_name, model.symmetry.kind) == ("cube", "box", "discrete")


def test_gltf_with_external_buffer(tmp_path: Path) -> None:
    v, f = unit_cube_mesh()
    files = trimesh.Trimesh(v, f, process=False).export(file_type="gltf")
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    model = load_cad(tmp_path / "model.gltf")
    assert len(model.faces) == 12 and model.unit == "m"


def test_scene_nodes_become_parts_with_transforms(tmp_path: Path) -> None:
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    box.visual.face_colors = [255, 0, 0, 255]
    cyl = trimesh.creation.cylinder(radius=0.25, height=1.0, sections=16)
    scene = trimesh.Scene()
    scene.add_geometry(box, node_name="body", geom_name="body")
    T = trimesh.transformations.translation_matrix([3.0, 0.0, 0.0])
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    scene.add_geometry(cyl, node_name="stem", geom_name="stem", transform=T @ mirror)
    path = tmp_path / "two_parts.glb"
    scene.export(path)
    model = load_cad(path)
    assert sorted(model.part_names) == ["body", "stem"]
    assert len(model.part_faces("body")) == 12
    assert len(model.part_faces("stem")) == len(cyl.faces)
    stem_v = model.vertices_m[np.unique(model.faces[model.part_faces("stem")])]
    np.testing.assert_allclose(stem_v.mean(axis=0), [3.0, 0.0, 0.0], atol=1e-6)
    # the mirroring node transform must not turn the stem inside out
    stem = trimesh.Trimesh(model.vertices_m, model.faces[model.part_faces("stem")], process=True)
    assert stem.volume > 0
    assert model.vertex_colors is not None or model.face_colors is not None


def test_symmetry_argument_forms(uuv_cad_dir: Path) -> None:
    path = uuv_cad_dir / "rov_bop_panel/meshes/Valve.dae"
    assert load_cad(path).symmetry.kind == "none"
    assert load_cad(path, symmetry="continuous_z").symmetry.kind == "continuous"
    sym = Symmetry.cyclic((0, 0, 1), 2)
    assert load_cad(path, symmetry=sym).symmetry is sym
    with pytest.raises(InputError, match="unknown symmetry name"):
        load_cad(path, symmetry="spherical")


def test_missing_file_raises_input_error(tmp_path: Path) -> None:
    path = tmp_path / "nope.ply"
    with pytest.raises(InputError, match=r"not found: '.*nope\.ply'"):
        load_cad(path)


def test_directory_raises_input_error(tmp_path: Path) -> None:
    d = tmp_path / "dir.ply"
    d.mkdir()
    with pytest.raises(InputError, match="dir.ply' is not a file"):
        load_cad(d)


def test_bad_extension_raises_input_error(tmp_path: Path) -> None:
    path = tmp_path / "part.sldprt"  # a native SolidWorks part (STEP and IGES are read, see test_cad_step.py)
    path.write_text("not a mesh")
    with pytest.raises(InputError, match=r"part\.sldprt' has unsupported extension '\.sldprt'.*PLY or OBJ"):
        load_cad(path)


def test_empty_mesh_raises_input_error(tmp_path: Path) -> None:
    path = tmp_path / "points.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(path)
    with pytest.raises(InputError, match=r"points\.ply' has no triangle faces"):
        load_cad(path)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(InputError, match=r"empty\.obj"):
        load_cad(empty)


def test_all_degenerate_mesh_raises_input_error(tmp_path: Path) -> None:
    path = tmp_path / "flat.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(InputError, match="all 1 faces are degenerate"):
        load_cad(path)


@pytest.mark.parametrize("ext,payload", [("ply", b"ply\nformat garbage\n"), ("dae", b"<COLLADA><oops"),
                                         ("glb", b"glTF\x02\x00\x00\x00junk"), ("stl", b"\x00\x01")])
def test_unreadable_file_raises_input_error(tmp_path: Path, ext: str, payload: bytes) -> None:
    path = tmp_path / f"broken.{ext}"
    path.write_bytes(payload)
    with pytest.raises(InputError, match=rf"broken\.{ext}"):
        load_cad(path)


def test_unknown_unit_raises_unit_error(uuv_cad_dir: Path) -> None:
    with pytest.raises(UnitError, match="unknown unit 'km'"):
        load_cad(uuv_cad_dir / "rov_bop_panel/meshes/Valve.dae", unit="km")


def test_clean_false_keeps_file_vertices(uuv_cad_dir: Path) -> None:
    path = uuv_cad_dir / "rov_bop_panel/meshes/Valve.dae"
    raw = load_cad(path, clean=False)
    cleaned = load_cad(path)
    assert len(raw.vertices_m) == len(read_cad_parts(path).vertices) > len(cleaned.vertices_m)
    np.testing.assert_allclose(raw.extent, cleaned.extent)

"""STEP and IGES through OpenCASCADE: declared units, named assembly parts, tessellation tolerance, parts by name
in a scene file, and the subsea panel exported to STEP and read back. Files are written with OCP (dev extra)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from step_testdata import box, cylinder, mesh_solid, write_step

from cadalign.cad import load_cad
from cadalign.errors import InputError
from cadalign.formats.step import TessellationConfig, declared_unit


def _assembly(path: Path, unit: str) -> Path:
    """A 1 x 0.5 x 0.1 m plate with a valve (r 0.1 m, 0.3 m tall) standing on it."""
    return write_step(path, {"plate": box((1.0, 0.5, 0.1)), "valve_1": cylinder(0.1, 0.3, (0.5, 0.25, 0.1))}, unit)


@pytest.mark.parametrize(("unit", "m_per_unit"), [("mm", 1e-3), ("in", 0.0254), ("m", 1.0)])
def test_step_unit_comes_from_the_file_and_geometry_is_metres(tmp_path: Path, unit: str, m_per_unit: float) -> None:
    path = _assembly(tmp_path / f"panel_{unit}.step", unit)
    assert declared_unit(path) == pytest.approx(m_per_unit)
    model = load_cad(path)
    assert model.unit == unit and model.part_names == ("plate", "valve_1")
    assert np.allclose(model.vertices_m.min(0), 0, atol=1e-6)
    assert np.allclose(model.vertices_m.max(0), [1.0, 0.5, 0.4], atol=1e-5)
    valve = model.vertices_m[np.unique(model.faces[model.part_labels == 1])]
    assert np.allclose(valve.min(0), [0.4, 0.15, 0.1], atol=1e-5)


def test_tessellation_tolerance_bounds_the_surface_error(tmp_path: Path) -> None:
    """The valve's triangles lie within linear_m of the true cylinder (r = 0.1 m), and a finer tolerance gives
    more triangles."""
    path = _assembly(tmp_path / "panel.step", "mm")
    counts = []
    for tol in (0.005, 0.0005):
        m = load_cad(path, part="valve_1", tessellation=TessellationConfig(linear_m=tol, angular_rad=3.0),
                     clean=False)
        tri = m.vertices_m[m.faces]
        centres = tri.mean(axis=1)  # a triangle's centre is where it sags furthest from the surface
        side = np.abs(np.abs(centres[:, 2] - 0.25) - 0.15) > 1e-6  # not on the end caps
        r = np.linalg.norm(centres[side, :2] - [0.5, 0.25], axis=1)
        assert 0 < (0.1 - r).max() <= tol  # sags inwards, by at most the tolerance
        r_v = np.linalg.norm(m.vertices_m[:, :2] - [0.5, 0.25], axis=1)
        assert np.abs(r_v[r_v > 0.01] - 0.1).max() < 1e-5  # vertices on the surface (cap centres aside)
        counts.append(len(m.faces))
    assert counts[1] > 2 * counts[0]


def test_a_part_by_name_and_a_missing_one(tmp_path: Path) -> None:
    path = _assembly(tmp_path / "panel.step", "in")
    valve = load_cad(path, part="valve_1")
    assert valve.part_names == ("valve_1",) and valve.unit == "in"
    assert np.allclose(valve.extent, [0.2, 0.2, 0.3], atol=2e-3)
    with pytest.raises(InputError, match=r"no part named 'valve_9'; its parts: plate, valve_1"):
        load_cad(path, part="valve_9")


def test_iges_unit_from_the_global_section(tmp_path: Path) -> None:
    path = write_step(tmp_path / "plate.igs", {"plate": box((1.0, 0.5, 0.1))}, "mm", iges=True)
    model = load_cad(path)
    assert model.unit == "mm" and np.allclose(model.extent, [1.0, 0.5, 0.1], atol=1e-5)
    # the same numbers declared as inches: OpenCASCADE scales them, the unit is recorded
    text = path.read_text(encoding="latin-1").replace(",2,2HMM,", ",1,2HIN,")  # same length: IGES is column-bound
    (tmp_path / "plate_in.igs").write_text(text, encoding="latin-1")
    inch = load_cad(tmp_path / "plate_in.igs")
    assert inch.unit == "in" and np.allclose(inch.extent, np.array([1000, 500, 100]) * 0.0254, rtol=1e-4)


def test_scene_object_refers_to_a_step_part_by_name(tmp_path: Path) -> None:
    """``source = "panel.step#valve_1"`` in a scene's [[objects]] loads that part only, in metres."""
    from cadalign.sim.scene import build_scene
    from cadalign.sim.spec import load_scene
    from cadalign.testing.tiny_scene import write_tiny_scene

    _assembly(tmp_path / "panel.step", "in")
    spec_path = write_tiny_scene(tmp_path / "tiny.toml", effects=[])
    text = spec_path.read_text()
    first = text.index('source = "')
    end = text.index('"', first + len('source = "'))
    spec_path.write_text(text[:first] + 'source = "panel.step#valve_1"' + text[end + 1:])
    scene = build_scene(load_scene(spec_path), spec_path, width=8, height=8)
    mesh = scene.models[1]
    assert np.allclose(mesh.extents, [0.2, 0.2, 0.3], atol=2e-3)


def test_subsea_panel_exported_to_step_reads_back_within_tolerance(tmp_path: Path, shared_data: Path) -> None:
    """UUV Simulator's rov_bop_panel (the panel and its valve, placed per model.sdf) written as one STEP assembly
    of faceted surfaces in millimetres, one named product per part: read back, every part matches its mesh within
    the tessellation tolerance both ways (vertices of each on the other's surface). A faceted STEP is the worst
    case for a STEP reader (a B-rep face per triangle): 5.6k triangles, 18 MB, ~8 s to read."""
    from cadalign.cad import load_sdf_model

    parts = load_sdf_model(shared_data / "uuv_subsea_cad" / "rov_bop_panel" / "model.sdf")
    placed, seen = {}, set()
    for name, model, T in parts:
        if id(model) in seen:  # valves 2-5 repeat valve_1's mesh elsewhere: reading them back again adds ~8 s
            continue
        seen.add(id(model))
        placed[name.replace("/", "_")] = (model.vertices_m @ T.R.T + T.t, model.faces)
    path = write_step(tmp_path / "panel.step", {n: mesh_solid(v, f) for n, (v, f) in placed.items()}, "mm")
    back = load_cad(path, clean=False)
    tol = TessellationConfig().linear_m
    assert back.unit == "mm" and set(back.part_names) == set(placed), back.part_names
    for i, name in enumerate(back.part_names):
        v_ref, f_ref = placed[name]
        sel = back.faces[back.part_labels == i]
        v_got = back.vertices_m[np.unique(sel)]
        assert _distance(v_ref, f_ref, v_got).max() <= tol
        assert _distance(back.vertices_m, sel, v_ref).max() <= tol


def _distance(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unsigned distance (m) of (N, 3) points to a triangle mesh (open3d's exact point-triangle query)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    mesh = o3d.t.geometry.TriangleMesh(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                                       o3d.core.Tensor(np.asarray(faces, np.int32)))
    scene.add_triangles(mesh)
    return scene.compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy()

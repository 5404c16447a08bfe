"""A camera inside a mesh part (a CAD file, a procedural valve or frame) is a clear ConfigError when the scene is
built; a camera in a part's bounding box but outside the part (a notch, an open frame) is fine. The test is the
generalised winding number of :mod:`cadalign.cad.inside`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from reliability_testdata import expect_error
from typer.testing import CliRunner

from cadalign.cad.inside import inside_mesh, winding_numbers
from cadalign.cli.main import app
from cadalign.errors import ConfigError, InputError

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")

SCENE = """
name = "clearance"
seed = 1
classes = ["background", "structure"]
[camera]
width = 32
height = 24
[trajectory]
kind = "orbit"
center = [{cx}, {cy}, 0.4]
radius_m = {radius}
height_m = {height}
frames = 3
fps = 1.0
jitter_m = 0.0
[[objects]]
name = "pump"
source = "{source}"
unit = "m"
class_name = "structure"
position = [0.0, 0.0, {pz}]
"""


def _cube(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(bounds=[lo, hi])


def _u_shape() -> trimesh.Trimesh:
    """A 2 x 2 x 1 m block with a 1 m wide notch through it along y (x in [-0.5, 0.5], z above 0.2 m)."""
    parts = [_cube((-1, -1, 0), (-0.5, 1, 1)), _cube((0.5, -1, 0), (1, 1, 1)), _cube((-0.5, -1, 0), (0.5, 1, 0.2))]
    return trimesh.util.concatenate(parts)


def _scene(tmp_path: Path, source: str, *, radius: float, height: float, cx: float = 0.0, cy: float = 0.0,
           pz: float = 0.0) -> Path:
    p = tmp_path / "scene.toml"
    p.write_text(SCENE.format(source=source, radius=radius, height=height, cx=cx, cy=cy, pz=pz))
    return p


def _build(path: Path) -> None:
    from cadalign.sim.scene import build_scene
    from cadalign.sim.spec import load_scene

    build_scene(load_scene(path), path, width=8, height=8)


def test_winding_numbers_of_a_closed_cube_a_holed_cube_and_bad_input() -> None:
    cube = _cube((0, 0, 0), (1, 1, 1))
    pts = np.array([[0.5, 0.5, 0.5], [0.01, 0.5, 0.99], [1.5, 0.5, 0.5], [-3.0, 7.0, 2.0], [0.0, 0.0, 0.0]])
    w = winding_numbers(cube.vertices, cube.faces, pts)
    np.testing.assert_allclose(w[:4], [1.0, 1.0, 0.0, 0.0], atol=1e-9)
    assert np.isfinite(w[4])  # a point on a vertex: finite, no division warning
    holed = cube.faces[1:]  # one of 12 triangles missing (a CAD export with a hole): still inside at the centre
    assert 0.5 < winding_numbers(cube.vertices, holed, pts[:1])[0] < 1.0
    assert inside_mesh(cube.vertices, cube.faces, pts).tolist() == [True, True, False, False, False]
    with pytest.raises(InputError, match="face indices"):
        winding_numbers(cube.vertices, cube.faces + 100, pts)


@settings(max_examples=20, deadline=None, derandomize=True, database=None)
@given(seed=st.integers(0, 2**16))
def test_inside_mesh_matches_the_exact_answer_for_an_icosphere(seed: int) -> None:
    """An icosphere of radius 1: points clearly inside (r < 0.95) or outside (r > 1.01) are classified exactly."""
    sphere = trimesh.creation.icosphere(subdivisions=2)
    rng = np.random.default_rng(seed)
    p = rng.uniform(-1.5, 1.5, (200, 3))
    r = np.linalg.norm(p, axis=1)
    clear = (r < 0.95) | (r > 1.01)
    got = inside_mesh(sphere.vertices, sphere.faces, p)
    assert np.array_equal(got[clear], r[clear] < 1)


def test_camera_inside_a_cad_mesh_is_refused(tmp_path: Path) -> None:
    _cube((-0.5, -0.5, 0.0), (0.5, 0.5, 1.0)).export(tmp_path / "pump.obj")
    scene = _scene(tmp_path, "pump.obj", radius=0.2, height=0.5)
    expect_error("scene spec", "camera inside a CAD mesh object (OBJ file)", ConfigError, lambda: _build(scene),
                 "scene.toml", "the camera of frame 0", "inside object 'pump' (pump.obj)", "change the trajectory")


def test_camera_in_the_bounding_box_but_outside_the_mesh_is_fine(tmp_path: Path) -> None:
    _u_shape().export(tmp_path / "u.ply")
    _build(_scene(tmp_path, "u.ply", radius=0.1, height=0.6))  # in the notch: inside the box, outside the part
    with pytest.raises(ConfigError, match="inside object 'pump'"):
        _build(_scene(tmp_path, "u.ply", radius=0.1, height=0.6, cx=-0.75))  # in the left wall


def test_camera_inside_the_bundled_hot_stab_is_refused(tmp_path: Path, shared_data: Path) -> None:
    """The real CAD (a DAE export, 1092 faces, 0.52 x 0.06 x 0.11 m): a camera 0.1 m along its shaft is refused,
    one 0.2 m beside it is not."""
    source = "data:uuv_subsea_cad/hot_stab/meshes/HotStab.dae"
    expect_error("scene spec", "camera inside a CAD mesh object (the bundled hot stab DAE)", ConfigError,
                 lambda: _build(_scene(tmp_path, source, radius=0.005, height=0.5, cx=0.1, pz=0.5)),
                 "inside object 'pump' (data:uuv_subsea_cad/hot_stab/meshes/HotStab.dae)")
    _build(_scene(tmp_path, source, radius=0.005, height=0.5, cx=0.1, cy=0.2, pz=0.5))


def test_sim_cli_refuses_a_camera_inside_a_cad_mesh(tmp_path: Path) -> None:
    _cube((-0.5, -0.5, 0.0), (0.5, 0.5, 1.0)).export(tmp_path / "pump.stl")
    scene = _scene(tmp_path, "pump.stl", radius=0.2, height=0.5)
    res = CliRunner().invoke(app, ["sim", str(scene), "--out", str(tmp_path / "o"), "--no-video"])
    out = "".join(res.output.split())
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert "inside object 'pump' (pump.stl)".replace(" ", "") in out
    assert not (tmp_path / "o" / "frames").exists()

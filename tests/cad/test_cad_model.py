"""CadModel validation and derived geometry (bounding box, exact diameter), and Symmetry."""

from __future__ import annotations

import numpy as np
import pytest
from cad_testdata import unit_cube_mesh
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.distance import pdist

from cadalign.cad import CadModel, Symmetry, max_pairwise_distance
from cadalign.errors import InputError


def test_unit_cube_geometry(unit_cube: CadModel) -> None:
    assert unit_cube.diameter_m == pytest.approx(np.sqrt(3), abs=1e-12)
    np.testing.assert_array_equal(unit_cube.bbox_min, [0, 0, 0])
    np.testing.assert_array_equal(unit_cube.bbox_max, [1, 1, 1])
    np.testing.assert_array_equal(unit_cube.extent, [1, 1, 1])
    assert unit_cube.to_trimesh().is_watertight and unit_cube.to_trimesh().volume == pytest.approx(1.0)
    assert unit_cube.part_names == ("cube",) and unit_cube.class_name == "cube"
    assert unit_cube.part_labels.dtype == np.int32 and unit_cube.faces.dtype == np.int64
    assert unit_cube.symmetry.kind == "none"


def test_arrays_are_read_only(unit_cube: CadModel) -> None:
    with pytest.raises(ValueError):
        unit_cube.vertices_m[0, 0] = 5.0
    with pytest.raises(ValueError):
        unit_cube.part_labels[0] = 1


def test_bbox_ignores_unreferenced_vertices() -> None:
    v, f = unit_cube_mesh()
    m = CadModel("c", np.concatenate([v, [[100.0, 0, 0]]]), f)
    np.testing.assert_array_equal(m.bbox_max, [1, 1, 1])
    assert m.diameter_m == pytest.approx(np.sqrt(3))


@pytest.mark.parametrize("kwargs,match", [
    (dict(faces=np.array([[0, 1, 9]])), "face indices"),
    (dict(faces=np.zeros((0, 3), int)), "no faces"),
    (dict(faces=np.array([[0.0, 1.0, 2.0]])), "integer"),
    (dict(vertices_m=np.full((3, 3), np.nan)), "finite"),
    (dict(unit="km"), "unknown unit"),
    (dict(part_labels=np.array([1])), "part_labels"),
    (dict(vertex_colors=np.zeros((2, 4))), "vertex_colors"),
])
def test_invalid_model_raises(kwargs: dict, match: str) -> None:
    base = dict(name="t", vertices_m=np.eye(3), faces=np.array([[0, 1, 2]]))
    with pytest.raises(InputError, match=match):
        CadModel(**{**base, **kwargs})


def test_colors_and_to_trimesh(unit_cube: CadModel) -> None:
    v, f = unit_cube_mesh()
    m = CadModel("c", v, f, face_colors=np.tile([255, 0, 0], (12, 1)))
    assert m.face_colors.shape == (12, 4) and np.all(m.face_colors[:, 3] == 255)
    assert m.to_trimesh().visual.kind == "face"
    assert m.to_trimesh(visuals=False).visual.kind is None
    assert m.vertex_colors_or_default().shape == (8, 4)
    assert unit_cube.vertex_colors_or_default() is None


def test_scaled_flips_winding_when_mirrored(unit_cube: CadModel) -> None:
    m = unit_cube.scaled((-1.0, 1.2, 1.2))
    np.testing.assert_allclose(m.extent, [1.0, 1.2, 1.2])
    assert m.to_trimesh().volume == pytest.approx(1.44)
    sym = CadModel("c", unit_cube.vertices_m, unit_cube.faces, symmetry=Symmetry.cyclic((0, 0, 1), 2, (0.5, 0.5, 0)))
    np.testing.assert_allclose(sym.scaled(2.0).symmetry.discrete[0][:3, 3], [2.0, 2.0, 0.0])
    assert sym.scaled((1, 1, 2)).symmetry.kind == "none"


def test_diameter_degenerate_sets() -> None:
    assert max_pairwise_distance(np.zeros((1, 3))) == 0.0
    assert max_pairwise_distance(np.zeros((5, 3))) == 0.0
    line = np.outer(np.linspace(-1, 2, 7), [1.0, 2.0, 2.0])
    assert max_pairwise_distance(line) == pytest.approx(9.0)
    square = np.array([[0, 0, 1], [3, 0, 1], [0, 4, 1], [3, 4, 1], [1, 1, 1]], float)
    assert max_pairwise_distance(square) == pytest.approx(5.0)


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(2, 60), st.just(3)),
              elements=st.floats(-100, 100, allow_nan=False, allow_infinity=False)))
def test_diameter_matches_brute_force(pts: np.ndarray) -> None:
    assert max_pairwise_distance(pts) == pytest.approx(pdist(pts).max(), rel=1e-9, abs=1e-9)


def _is_rotation_about(T: np.ndarray, axis: np.ndarray, point: np.ndarray) -> bool:
    R = T[:3, :3]
    ok_R = np.allclose(R @ R.T, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    fixes_axis = np.allclose(R @ axis, axis, atol=1e-12)
    fixes_line = np.allclose(T[:3, :3] @ (point + 0.7 * axis) + T[:3, 3], point + 0.7 * axis, atol=1e-12)
    return bool(ok_R and fixes_axis and fixes_line)


def test_continuous_discretize_rotates_about_axis() -> None:
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    offset = np.array([0.1, -0.2, 0.3])
    sym = Symmetry.continuous(axis * 3.0, offset)  # the axis is normalised
    np.testing.assert_allclose(sym.axis, axis)
    Ts = sym.discretize(8)
    assert len(Ts) == 8 and all(T.shape == (4, 4) for T in Ts)
    np.testing.assert_allclose(Ts[0], np.eye(4), atol=1e-15)
    p = offset + np.array([2.0, -1.0, 0.0])  # a point off the axis (perpendicular to it)
    angles = []
    for T in Ts:
        assert _is_rotation_about(T, axis, offset)
        q = T[:3, :3] @ p + T[:3, 3]
        u, w = p - offset, q - offset
        assert np.linalg.norm(w) == pytest.approx(np.linalg.norm(u))
        angles.append(np.arctan2(np.dot(axis, np.cross(u, w)), np.dot(u, w)) % (2 * np.pi))
    np.testing.assert_allclose(angles, 2 * np.pi * np.arange(8) / 8, atol=1e-9)


def test_discrete_and_combined_symmetries() -> None:
    z4 = Symmetry.from_name("discrete_z4")
    assert z4.kind == "discrete" and len(z4.discrete) == 3
    Ts = z4.discretize(100)  # n is ignored for discrete groups
    assert len(Ts) == 4
    np.testing.assert_allclose(Ts[2][:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # 180 deg about x
    both = Symmetry("continuous", (flip,), np.array([0, 0, 1.0]), None)
    assert len(both.discretize(6)) == 12
    assert Symmetry.none().discretize(5)[0].tolist() == np.eye(4).tolist()
    assert Symmetry.from_name("continuous_y").axis.tolist() == [0.0, 1.0, 0.0]
    assert Symmetry.discrete_from([flip.ravel()]).discrete[0].shape == (4, 4)


@pytest.mark.parametrize(("name", "half_turn"), [("discrete_x2", [1.0, -1.0, -1.0]),
                                               ("discrete_y2", [-1.0, 1.0, -1.0]),
                                               ("discrete_z2", [-1.0, -1.0, 1.0])])
def test_half_turns_about_each_axis(name: str, half_turn: list[float]) -> None:
    Ts = Symmetry.from_name(name).discretize()
    assert len(Ts) == 2
    np.testing.assert_allclose(Ts[1][:3, :3], np.diag(half_turn), atol=1e-12)
    assert len(Symmetry.from_name(name[:-1] + "4").discretize()) == 4


@pytest.mark.parametrize("make,match", [
    (lambda: Symmetry("continuous"), "needs an axis"),
    (lambda: Symmetry("discrete"), "at least one"),
    (lambda: Symmetry("spiral"), "unknown symmetry kind"),
    (lambda: Symmetry.continuous((0, 0, 0)), "non-zero"),
    (lambda: Symmetry.discrete_from([np.diag([1.0, 1.0, -1.0, 1.0])]), "proper rotation"),
    (lambda: Symmetry.discrete_from([np.eye(3)]), r"\(4, 4\)"),
    (lambda: Symmetry("none", axis=np.ones(3)), "takes no axis"),
    (lambda: Symmetry.cyclic((0, 0, 1), 1), "order >= 2"),
    (lambda: Symmetry.from_name("continuous_w"), "unknown symmetry name"),
    (lambda: Symmetry.none().discretize(0), "n >= 1"),
])
def test_invalid_symmetry_raises(make, match: str) -> None:
    with pytest.raises(InputError, match=match):
        make()

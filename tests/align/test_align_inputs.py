"""Input checks of the core: SfM points, coarse-method inputs, CAD parts and exact surface distances."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.align import AlignConfig, align, sample_surface
from cadalign.align.core import check_points
from cadalign.cad import CadModel
from cadalign.errors import InputError
from cadalign.types import Rigid3, Sim3


@pytest.fixture(scope="module")
def cube() -> CadModel:
    """The unit cube [0, 1]^3."""
    import trimesh

    m = trimesh.creation.box(extents=(1, 1, 1))
    return CadModel("cube", np.asarray(m.vertices) + 0.5, np.asarray(m.faces))


def test_check_points_drops_non_finite_rows(caplog):
    pts = np.random.default_rng(0).normal(size=(20, 3))
    pts[3, 1], pts[7, 2] = np.nan, np.inf
    with caplog.at_level("WARNING"):
        out = check_points(pts)
    assert out.shape == (18, 3) and np.all(np.isfinite(out))
    assert "dropped 2 non-finite points" in caplog.text


@pytest.mark.parametrize(("pts", "match"), [(np.zeros((5, 2)), r"shape \(N, 3\)"), (np.zeros((4, 3)), "at least 10"),
                                            (np.full((30, 3), np.nan), "0 finite points")])
def test_check_points_rejects(pts, match):
    with pytest.raises(InputError, match=match):
        check_points(pts)


@pytest.mark.parametrize(("coarse", "match"), [("picks", "needs point correspondences"), ("prior", "needs a prior")])
def test_coarse_method_without_its_input(cube, coarse, match):
    with pytest.raises(InputError, match=match):
        align(np.random.default_rng(0).normal(size=(50, 3)), [cube], AlignConfig(coarse=coarse))


def test_sample_surface_parts_and_poses(cube):
    surf = sample_surface([cube, (cube, Rigid3(np.eye(3), (10.0, 0, 0)))], 4000, seed=0)
    assert surf.points_m.shape == (4000, 3) and surf.part_names == ("cube", "cube")
    second = surf.part_index == 1
    assert 0.4 < second.mean() < 0.6  # equal areas get equal shares
    assert np.all(surf.points_m[second, 0] >= 10.0 - 1e-9) and np.all(surf.points_m[~second, 0] <= 1.0 + 1e-9)
    assert np.allclose(np.linalg.norm(surf.normals, axis=1), 1.0)
    again = sample_surface([cube, (cube, Rigid3(np.eye(3), (10.0, 0, 0)))], 4000, seed=0)
    assert np.array_equal(surf.points_m, again.points_m)


@pytest.mark.parametrize(("parts", "match"), [([], "no CAD parts"), (["cube.obj"], "expected a CadModel"),
                                              ([("a", "b")], r"expected \(CadModel, Rigid3\)")])
def test_sample_surface_rejects(parts, match):
    with pytest.raises(InputError, match=match):
        sample_surface(parts, 100, seed=0)


def test_exact_distances_on_the_cube(cube):
    surf = sample_surface([cube], 2000, seed=0)
    q = np.array([[2.0, 0.5, 0.5], [0.5, 0.5, 0.5], [0.5, 0.5, -0.25], [1.0, 1.0, 1.0], [2.0, 2.0, 1.0]])
    assert np.allclose(surf.distances(q), [1.0, 0.5, 0.25, 0.0, np.sqrt(2)], atol=1e-6)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(st.lists(st.tuples(*[st.floats(-3, 4)] * 3), min_size=1, max_size=20),
       st.floats(-1e6, 1e6), st.floats(1e-3, 1e3))
def test_exact_distance_never_exceeds_the_sample_distance(cube, xyz, offset, scale):
    """Also far from the origin and at any size: the float32 ray caster works relative to the centroid."""
    T = Sim3(scale, np.eye(3), np.full(3, offset))
    moved = CadModel("cube", T.apply(cube.vertices_m), cube.faces)
    surf = sample_surface([moved], 3000, seed=1)
    q = T.apply(np.array(xyz))
    exact = surf.distances(q)
    nn, _ = surf.tree.query(q)
    assert np.all(exact <= nn + 1e-6 * scale)
    inside = np.all((np.array(xyz) > 0) & (np.array(xyz) < 1), axis=1)
    expected = np.min(np.abs(np.concatenate([np.array(xyz), 1 - np.array(xyz)], axis=1)), axis=1) * scale
    assert np.allclose(exact[inside], expected[inside], atol=1e-5 * scale)

"""clean_mesh: exact counts of what is fixed, and per-face data that follows the surviving faces."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from cad_testdata import UUV_DAE, unit_cube_mesh
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.cad import CadModel, clean_mesh, clean_model, edge_topology, load_cad
from cadalign.errors import InputError


def _dirty_cube() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A two-part cube (labels 0/1) with every kind of defect injected, in a known amount."""
    v, f = unit_cube_mesh()
    labels = np.array([0] * 6 + [1] * 6, dtype=np.int32)
    # 8 duplicated vertices (exact copies) and 2 near-copies within 1e-8 m, used by re-pointed faces
    dup = np.concatenate([v, v[:2] + 1e-8])
    v2 = np.concatenate([v, dup, [[5.0, 5.0, 5.0], [np.nan, 0.0, 0.0]]])  # + 1 stray + 1 NaN vertex
    f2 = f.copy()
    f2[::2] += 8  # half of the faces now use the duplicated vertices
    f2[0, 0] = 16  # a near-copy of vertex 0
    extra = np.array([
        [0, 1, 1],       # degenerate: repeated index
        [0, 8, 1],       # degenerate after merging (8 is a copy of 0)
        [0, 1, 0 + 16],  # degenerate after merging (16 is a near-copy of 0)
        [0, 1, 2],       # valid (the other diagonal of the x=0 side): kept
        [3, 2, 1],       # valid, (1, 2, 3) is no existing face: kept
        [3, 0, 1],       # duplicate of face 0 (0, 1, 3) in another order
        [11, 9, 8],      # duplicate of face 0 through merged copies (8, 9, 11) == (0, 1, 3)
        [0, 1, 19],      # uses the NaN vertex
    ])
    # a zero-area face from three distinct collinear vertices: add two midpoints on edge 0-1
    mid = np.array([[0.0, 0.0, 0.25], [0.0, 0.0, 0.75]])
    n = len(v2)
    v3 = np.concatenate([v2, mid])
    extra = np.concatenate([extra, [[0, n, n + 1]]])
    f3 = np.concatenate([f2, extra])
    labels3 = np.concatenate([labels, [1, 1, 0, 0, 1, 1, 0, 1, 0]]).astype(np.int32)
    return v3, f3, labels3


def test_clean_counts_and_labels() -> None:
    v, f, labels = _dirty_cube()
    out_v, out_f, rep = clean_mesh(v, f, merge_tol_m=1e-6)
    assert rep.vertices_in == len(v) and rep.faces_in == len(f)
    assert rep.merged_vertices == 10  # 8 exact + 2 near copies
    assert rep.nonfinite_faces == 1
    assert rep.degenerate_faces == 3
    assert rep.zero_area_faces == 1
    assert rep.duplicate_faces == 2
    # stray (5,5,5), the NaN vertex and the two collinear midpoints are no longer used
    assert rep.unreferenced_vertices == 4
    assert rep.faces_out == len(f) - 7 == 14
    assert rep.vertices_out == len(v) - 10 - 4 == 8
    assert rep.vertices_out + rep.merged_vertices + rep.unreferenced_vertices == rep.vertices_in
    # the 12 cube faces survive in order, plus the two extra non-duplicate triangles
    np.testing.assert_array_equal(rep.kept_face_ids, [*range(12), 15, 16])
    new_labels = labels[rep.kept_face_ids]
    np.testing.assert_array_equal(new_labels, [0] * 6 + [1] * 6 + [0, 1])
    # every output face is the same triangle (same positions) as the input face it came from
    np.testing.assert_allclose(out_v[out_f], v[f[rep.kept_face_ids]], atol=1e-6)
    np.testing.assert_array_equal(out_v, v[rep.vertex_source])
    assert out_f.dtype == np.int64 and out_f.max() < len(out_v)


def test_clean_model_carries_labels_and_colors(caplog: pytest.LogCaptureFixture) -> None:
    v, f, labels = _dirty_cube()
    v = np.nan_to_num(v)  # CadModel refuses NaN vertices
    vc = np.zeros((len(v), 4), np.uint8)
    vc[:, 0] = np.arange(len(v))  # colour = vertex index
    fc = np.zeros((len(f), 4), np.uint8)
    fc[:, 1] = np.arange(len(f))  # colour = face index
    model = CadModel("dirty", v, f, part_labels=labels, part_names=("a", "b"), vertex_colors=vc, face_colors=fc)
    with caplog.at_level(logging.INFO, logger="cadalign.cad.clean"):
        cleaned, rep = clean_model(model)
    assert "cleaned CAD 'dirty'" in caplog.text and "merged vertices" in caplog.text
    np.testing.assert_array_equal(cleaned.part_labels, labels[rep.kept_face_ids])
    np.testing.assert_array_equal(cleaned.face_colors[:, 1], rep.kept_face_ids)
    np.testing.assert_array_equal(cleaned.vertex_colors[:, 0], rep.vertex_source)
    assert cleaned.part_names == ("a", "b") and cleaned.name == "dirty"


def test_clean_is_idempotent_on_clean_mesh() -> None:
    v, f = unit_cube_mesh()
    out_v, out_f, rep = clean_mesh(v, f)
    assert not rep.changed
    np.testing.assert_array_equal(out_v, v)
    np.testing.assert_array_equal(out_f, f)
    assert (rep.non_manifold_edges, rep.boundary_edges) == (0, 0)
    assert "nothing to fix" in rep.summary()


def test_zero_tolerance_merges_exact_duplicates_only() -> None:
    v, f = unit_cube_mesh()
    v2 = np.concatenate([v, v[:1], v[:1] + 1e-9])
    f2 = f.copy()
    f2[0, 0] = 8
    f2[1, 0] = 9
    _, _, rep = clean_mesh(v2, f2, merge_tol_m=0.0)
    assert rep.merged_vertices == 1
    assert rep.vertices_out == 9


def test_edge_topology_counts() -> None:
    v, f = unit_cube_mesh()
    assert edge_topology(f) == (0, 0)
    assert edge_topology(f[:-1]) == (0, 3)  # one missing triangle opens 3 edges
    fin = np.concatenate([f, [[0, 1, 8]], [[1, 0, 9]]])  # two fins on edge 0-1: 4 faces share it
    assert edge_topology(fin) == (1, 4)
    assert edge_topology(np.zeros((0, 3), int)) == (0, 0)


@pytest.mark.parametrize("rel", UUV_DAE[:4])
def test_topology_matches_pymeshlab(uuv_cad_dir: Path, rel: str) -> None:
    pymeshlab = pytest.importorskip("pymeshlab")
    model = load_cad(uuv_cad_dir / rel)
    _, _, rep = clean_mesh(model.vertices_m, model.faces)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(model.vertices_m, model.faces.astype(np.int32)))
    topo = ms.get_topological_measures()
    assert rep.non_manifold_edges == topo["non_two_manifold_edges"]
    assert rep.boundary_edges == topo["boundary_edges"]
    assert not rep.changed  # load_cad already cleaned it


def test_clean_rejects_bad_input() -> None:
    v, f = unit_cube_mesh()
    with pytest.raises(InputError, match="face indices"):
        clean_mesh(v, f + 100)
    with pytest.raises(InputError, match=r"\(V, 3\)"):
        clean_mesh(v[:, :2], f)
    with pytest.raises(InputError, match="integer"):
        clean_mesh(v, f.astype(float))
    with pytest.raises(InputError, match="tolerances"):
        clean_mesh(v, f, merge_tol_m=-1.0)


@settings(max_examples=40, deadline=None)
@given(
    n_v=st.integers(3, 30),
    n_f=st.integers(1, 60),
    seed=st.integers(0, 2**31 - 1),
    snap=st.sampled_from([0.0, 0.5]),
)
def test_clean_invariants_on_random_soups(n_v: int, n_f: int, seed: int, snap: float) -> None:
    """Random triangle soups (with many coincident points when snapped to a grid)."""
    rng = np.random.default_rng(seed)
    v = rng.random((n_v, 3))
    if snap:
        v = np.round(v / snap) * snap
    f = rng.integers(0, n_v, size=(n_f, 3))
    labels = rng.integers(0, 3, size=n_f)
    out_v, out_f, rep = clean_mesh(v, f)
    assert len(out_f) == rep.faces_out == len(rep.kept_face_ids)
    assert rep.faces_out + rep.degenerate_faces + rep.zero_area_faces + rep.duplicate_faces + rep.nonfinite_faces \
        == rep.faces_in
    assert rep.vertices_out + rep.merged_vertices + rep.unreferenced_vertices == rep.vertices_in
    assert np.all(np.diff(rep.kept_face_ids) > 0)
    if len(out_f):
        np.testing.assert_allclose(out_v[out_f], v[f[rep.kept_face_ids]], atol=1e-6)
        assert len(np.unique(np.sort(out_f, axis=1), axis=0)) == len(out_f)  # no duplicates left
        assert np.all(out_f[:, 0] != out_f[:, 1]) and np.all(out_f[:, 1] != out_f[:, 2])
        assert set(np.unique(out_f)) == set(range(len(out_v)))  # no unreferenced vertex left
    _ = labels[rep.kept_face_ids]  # per-face data indexes cleanly
    again_v, again_f, again = clean_mesh(out_v, out_f)
    assert not again.changed

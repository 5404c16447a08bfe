"""Map file and PLY round trips, and map metrics on exact hand cases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cadalign.errors import InputError
from cadalign.fuse.base import LabelledGeometry
from cadalign.fuse.map_io import load_map, read_ply, write_ply
from cadalign.metrics.map import CadTruth, map_metrics, point_truth_labels, sample_surface, visible_mask
from cadalign.types import Camera, Rigid3


def _square(z: float = 0.0, size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[0, 0, z], [size, 0, z], [size, size, z], [0, size, z]], dtype=np.float64)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _geom(points: np.ndarray, labels: np.ndarray, faces: np.ndarray | None = None,
          n_classes: int = 3) -> LabelledGeometry:
    probs = np.full((len(points), n_classes), 0.1, np.float32)
    probs[np.arange(len(points)), labels] = 1 - 0.1 * (n_classes - 1)
    return LabelledGeometry(points, np.tile([0, 0, 1.0], (len(points), 1)).astype(np.float32),
                            np.full((len(points), 3), 200, np.uint8), labels.astype(np.int64), probs, faces)


@pytest.mark.parametrize("with_faces", [True, False])
def test_ply_round_trip(tmp_path: Path, with_faces: bool) -> None:
    v, f = _square()
    v = v + [5.0e6, 4.0e5, 0.0]  # UTM-sized: written as double
    g = _geom(v, np.array([0, 1, 2, 1]), f if with_faces else None)
    vert, faces = read_ply(write_ply(g, tmp_path / "m.ply"))
    np.testing.assert_array_equal(np.stack([vert["x"], vert["y"], vert["z"]], 1), v)
    np.testing.assert_array_equal(vert["class"], [0, 1, 2, 1])
    np.testing.assert_array_equal(vert["red"], 200)
    np.testing.assert_allclose(vert["confidence"], 0.8, rtol=1e-6)
    if with_faces:
        np.testing.assert_array_equal(faces, f)
    else:
        assert faces is None


def test_ply_is_readable_by_open3d(tmp_path: Path) -> None:
    import open3d as o3d

    v, f = _square()
    mesh = o3d.io.read_triangle_mesh(str(write_ply(_geom(v, np.array([0, 1, 2, 1]), f), tmp_path / "m.ply")))
    assert len(mesh.vertices) == 4 and len(mesh.triangles) == 2


def test_corrupt_map_file_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "map.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(InputError, match="is not a cadalign map file"):
        load_map(bad)
    with pytest.raises(InputError, match="map file not found"):
        load_map(tmp_path / "missing.npz")


def test_metrics_exact_on_a_square() -> None:
    v, f = _square()
    truth = CadTruth(((v, f, 1),), ("background", "structure"))
    samples, cls = sample_surface(truth, 0.05, seed=0)
    assert len(samples) == 400 and np.all(cls == 1) and np.allclose(samples[:, 2], 0)
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 41), np.linspace(0, 1, 41)), -1).reshape(-1, 2)
    on = np.concatenate([grid, np.zeros((len(grid), 1))], 1)
    m = map_metrics(on, np.ones(len(on), int), None, truth, samples)
    assert m["completeness_within_2cm"] == 1.0 and m["accuracy_mean_m"] < 1e-6 and m["label_accuracy"] == 1.0
    # the same map 3 cm off the CAD: nothing within 2 cm, everything within 5 cm
    m = map_metrics(on + [0, 0, 0.03], np.ones(len(on), int), None, truth, samples)
    assert m["completeness_within_2cm"] == 0.0 and m["completeness_within_5cm"] == 1.0
    assert m["accuracy_mean_m"] == pytest.approx(0.03, abs=1e-6)
    # wrong labels on half the points; truth from the nearest CAD part
    labels = (np.arange(len(on)) % 2).astype(int)
    m = map_metrics(on, labels, None, truth, samples)
    assert m["label_accuracy"] == pytest.approx(np.mean(labels == 1))
    assert m["iou_per_class"]["structure"] == pytest.approx(np.mean(labels == 1))


def test_visibility_and_point_truth_hand_case() -> None:
    cam = Camera(np.array([[10.0, 0, 5], [0, 10.0, 5], [0, 0, 1]]), 10, 10)
    T = Rigid3()  # camera at the origin looking down +z
    pts = np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [10.0, 0.0, 2.0]])
    depth = np.full((10, 10), 2.0)
    cls = np.full((10, 10), 2)
    assert visible_mask(pts, [(cam, T, depth)], 0.1, 20.0, 0.05).tolist() == [True, False, False]
    assert point_truth_labels(pts, [(cam, T, depth, cls)], 3, 20.0, 0.05).tolist() == [2, -1, -1]


def _reference_votes(points, views, n_classes, depth_max_m, tol_m):
    """The first implementation: every point projected and rounded in every view, one bincount per view."""
    votes = np.zeros((len(points), n_classes), dtype=np.int64)
    for cam, T, depth, cls in views:
        pc = points @ T.R.T + T.t
        z = pc[:, 2]
        ok = (z > 0) & (z <= depth_max_m)
        u = np.floor(np.where(ok, pc[:, 0] / np.where(ok, z, 1) * cam.fx + cam.cx, -1)).astype(np.int64)
        v = np.floor(np.where(ok, pc[:, 1] / np.where(ok, z, 1) * cam.fy + cam.cy, -1)).astype(np.int64)
        ok &= (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        idx = np.flatnonzero(ok)
        idx = idx[np.abs(depth[v[idx], u[idx]] - z[idx]) <= tol_m]
        np.add.at(votes, (idx, cls[v[idx], u[idx]]), 1)
    return np.where(votes.sum(1) > 0, votes.argmax(1), -1), votes.sum(1) > 0


def test_point_truth_and_visibility_equal_projecting_every_point() -> None:
    """Only the points in a view's depth range are rounded, and votes are counted in batches of views: the same
    labels and visibility as projecting every point in every view (points behind, beside and beyond the camera,
    more views than counters so the batches flush)."""
    rng = np.random.default_rng(3)
    cam = Camera(np.array([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]]), 32, 24)
    points = rng.uniform([-3, -3, -2], [3, 3, 9], size=(60, 3))
    views = []
    for _ in range(40):
        T = Rigid3(np.linalg.qr(rng.normal(size=(3, 3)))[0] * [1, 1, 1], rng.normal(scale=0.3, size=3))
        if np.linalg.det(T.R) < 0:
            T = Rigid3(-T.R, T.t)
        depth = rng.uniform(0.5, 9, size=(24, 32))
        pc = T.apply(points)
        u = np.floor(pc[:, 0] / pc[:, 2] * 40 + 16).astype(int)
        v = np.floor(pc[:, 1] / pc[:, 2] * 40 + 12).astype(int)
        inside = (pc[:, 2] > 0) & (u >= 0) & (u < 32) & (v >= 0) & (v < 24)
        depth[v[inside], u[inside]] = pc[inside, 2] + rng.normal(scale=0.02, size=inside.sum())  # some agree
        views.append((cam, T, depth, rng.integers(0, 3, size=(24, 32))))
    labels, seen = _reference_votes(points, views, 3, 8.0, 0.03)
    assert 0 < seen.sum() < len(points)
    np.testing.assert_array_equal(point_truth_labels(points, views, 3, 8.0, 0.03), labels)
    np.testing.assert_array_equal(visible_mask(points, [v[:3] for v in views], 0.0, 8.0, 0.03), seen)

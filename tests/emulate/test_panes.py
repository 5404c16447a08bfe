"""Planar panes (Algorithm 1): plane fit + hull + fan, degenerate masks, random planes."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.emulate.panes import PaneConfig, extract_panes, pane_from_points, perimeter_pixels
from cadalign.errors import DegenerateGeometryError
from cadalign.geometry import depth_to_points, intrinsics, polygon_area, project_to_plane_2d

K = intrinsics(50.0, 50.0, 32.0, 24.0)


def _tilted_plane_depth(H: int = 48, W: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth of the plane n . x = d with n ~ (0.2, -0.1, -1) (facing the camera) and its normal."""
    n = np.array([0.2, -0.1, -1.0])
    n /= np.linalg.norm(n)
    d = -3.0  # n . x = d  ->  x on the plane in front of the camera
    rays = depth_to_points(K, np.ones((H, W)))[0]
    depth = d / (rays @ n)
    return depth, n, rays * depth[..., None]


def test_square_points_give_a_camera_facing_quad() -> None:
    pts = np.array([[0.0, 0, 5], [1, 0, 5], [1, 1, 5], [0, 1, 5], [0.5, 0.5, 5], [0.5, 0, 5]])
    plane, verts, faces = pane_from_points(pts)
    np.testing.assert_allclose(plane.normal, [0, 0, -1], atol=1e-12)  # towards the camera at the origin
    assert len(verts) == 4 and faces.shape == (2, 3)  # interior and edge points are not hull corners
    tri = verts[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(normals @ plane.normal > 0)  # fan triangles wind like the normal
    assert polygon_area(project_to_plane_2d(verts, plane)) == pytest.approx(1.0)


@pytest.mark.parametrize("pts", [np.zeros((0, 3)), np.ones((1, 3)), np.array([[0.0, 0, 1], [1, 1, 2], [2, 2, 3]]),
                                 np.tile([1.0, 2.0, 3.0], (5, 1))])
def test_degenerate_points_raise_the_clear_error(pts: np.ndarray) -> None:
    with pytest.raises(DegenerateGeometryError):
        pane_from_points(pts)


def test_degenerate_masks_are_skipped_with_a_reason() -> None:
    depth, _, pts = _tilted_plane_depth()
    valid = np.ones(depth.shape, bool)
    cfg = PaneConfig(min_pixels=1)
    empty = extract_panes(np.zeros(depth.shape, bool), pts, valid, cfg)
    assert empty.panes == () and empty.rejected == ()
    one = np.zeros(depth.shape, bool)
    one[10, 10] = True
    r = extract_panes(one, pts, valid, cfg)
    assert r.panes == () and len(r.rejected) == 1 and "perimeter pixels" in r.rejected[0][1]
    line = np.zeros(depth.shape, bool)
    line[20, 5:40] = True
    r = extract_panes(line, pts, valid, cfg)
    assert r.panes == () and "degenerate" in r.rejected[0][1] and "collinear" in r.rejected[0][1]
    small = extract_panes(one, pts, valid, PaneConfig(min_pixels=16))
    assert "min_pixels" in small.rejected[0][1]
    no_depth = np.zeros(depth.shape, bool)
    no_depth[5:20, 5:20] = True
    r = extract_panes(no_depth, pts, np.zeros(depth.shape, bool), cfg)
    assert "valid depth" in r.rejected[0][1]


def test_two_components_on_a_tilted_plane_and_a_non_planar_one() -> None:
    depth, n, pts = _tilted_plane_depth()
    mask = np.zeros(depth.shape, bool)
    mask[4:20, 4:24] = True
    mask[28:44, 30:60] = True
    bumpy = pts.copy()
    bumpy[30:42, 40:50] *= 1.5  # the second component's rim stays planar, its interior does not matter
    res = extract_panes(mask, bumpy, np.ones(depth.shape, bool), PaneConfig())
    assert len(res.panes) == 2 and res.rejected == ()
    for p in res.panes:
        assert np.degrees(np.arccos(min(1.0, p.plane.normal @ n))) < 1e-6
        assert len(p.vertices_m) >= 4 and len(p.faces) == len(p.vertices_m) - 2
    rough = pts.copy()
    rng = np.random.default_rng(0)
    rough[4:20, 4:24] *= rng.uniform(0.7, 1.3, (16, 20, 1))
    res = extract_panes(mask, rough, np.ones(depth.shape, bool), PaneConfig())
    assert len(res.panes) == 1 and "not planar" in res.rejected[0][1]


def test_perimeter_of_a_block_and_at_the_border() -> None:
    m = np.zeros((6, 6), bool)
    m[1:5, 1:5] = True
    assert len(perimeter_pixels(m)) == 12
    assert len(perimeter_pixels(np.ones((3, 3), bool))) == 8  # the image border counts as outside


@settings(max_examples=40, deadline=None)
@given(
    theta=st.floats(0.0, np.pi), phi=st.floats(0.0, 2 * np.pi), offset=st.floats(-1e3, 1e3),
    n=st.integers(3, 60), seed=st.integers(0, 2**31 - 1), noise=st.sampled_from([0.0, 1e-6]),
)
def test_random_planes_recover_the_normal_to_a_tenth_of_a_degree(theta, phi, offset, n, seed, noise) -> None:
    normal = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
    u = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-5, 5, (n, 2))
    xy[:3] = [[-5, -5], [5, -5], [0, 5]]  # a well-spread triangle: the plane is defined
    pts = offset * normal + xy[:, :1] * u + xy[:, 1:] * v + rng.normal(0, noise, (n, 3))
    plane, verts, faces = pane_from_points(pts)
    angle = np.degrees(np.arccos(np.clip(abs(plane.normal @ normal), 0, 1)))
    assert angle <= 0.1
    assert plane.normal @ (np.zeros(3) - plane.centroid) >= -1e-9 * (1 + abs(offset))  # faces the origin
    assert np.all(np.abs((verts - plane.centroid) @ plane.normal) < 1e-6 * (1 + abs(offset)))
    assert len(faces) == len(verts) - 2


@settings(max_examples=25, deadline=None)
@given(
    tilt=st.floats(0.0, 45.0), azim=st.floats(0.0, 360.0), dist=st.floats(0.5, 20.0),  # every pixel sees it
    r0=st.integers(0, 30), c0=st.integers(0, 40), h=st.integers(3, 17), w=st.integers(3, 23),
)
def test_algorithm1_on_random_planes_in_a_depth_image(tilt, azim, dist, r0, c0, h, w) -> None:
    """Mask -> component -> perimeter -> 3D -> SVD fit: the plane's normal within 0.1 degree, facing the camera."""
    t, a = np.radians(tilt), np.radians(azim)
    n = -np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])  # towards the camera
    rays = depth_to_points(K, np.ones((48, 64)))[0]
    depth = -dist / (rays @ n)  # n . x = -dist
    pts, valid = depth_to_points(K, depth)
    mask = np.zeros((48, 64), bool)
    mask[r0:r0 + h, c0:c0 + w] = True
    res = extract_panes(mask, pts, valid, PaneConfig(min_pixels=9))
    assert len(res.panes) == 1, res.rejected
    p = res.panes[0]
    assert np.degrees(np.arccos(np.clip(p.plane.normal @ n, -1, 1))) <= 0.1
    assert abs(p.plane.offset - dist) < 1e-6 * dist


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), density=st.floats(0.0, 0.2), invalid=st.floats(0.0, 0.9))
def test_random_sparse_masks_never_raise(seed: int, density: float, invalid: float) -> None:
    """Specks, lines and blobs with holes in the depth: every component is a pane or a rejection with a reason."""
    rng = np.random.default_rng(seed)
    depth, _, pts = _tilted_plane_depth()
    mask = rng.random(depth.shape) < density
    valid = rng.random(depth.shape) >= invalid
    res = extract_panes(mask, pts, valid, PaneConfig(min_pixels=1))
    assert len(res.panes) + len(res.rejected) == int(res.labels.max())
    assert all(isinstance(reason, str) and reason for _, reason in res.rejected)

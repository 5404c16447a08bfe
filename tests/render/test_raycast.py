"""Exact ray-cast ground truth: depth vs range, normals, labels, full masks, degenerate views."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.errors import InputError
from cadalign.raycast import RaycastRenderer, RenderMesh
from cadalign.types import Camera, Rigid3

CAM = Camera(np.array([[80.0, 0, 40.0], [0, 80.0, 30.0], [0, 0, 1]]), 80, 60)


def _look_at(eye: np.ndarray, target: np.ndarray) -> Rigid3:
    """T_world_from_cam for an OpenCV camera at ``eye`` looking at ``target`` (world z up)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Rigid3(np.stack([x, y, z], axis=1), eye)


def _cube(size: float, centre: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(size,) * 3, transform=trimesh.transformations.translation_matrix(centre))


def _mesh(m: trimesh.Trimesh, instance: int, class_id: int) -> RenderMesh:
    return RenderMesh(np.asarray(m.vertices), np.asarray(m.faces), instance, class_id)


def test_depth_range_normals_and_labels_of_a_cube() -> None:
    cube = _cube(1.0, (0, 0, 0))
    r = RaycastRenderer([_mesh(cube, 3, 2)], CAM)
    T = _look_at(np.array([0.0, -5.0, 0.0]), np.zeros(3))  # looking along +y at the face y = -0.5
    f = r.render(T)
    # the centre pixel ray (u = 40 -> centre 40.5) is almost on axis: depth is exactly 4.5
    assert f.depth_m[30, 40] == pytest.approx(4.5, abs=1e-5)
    hit = f.depth_m > 0
    np.testing.assert_allclose(f.depth_m[hit], 4.5, atol=1e-5)  # fronto-parallel face: z-depth constant
    assert np.all(f.range_m[hit] >= f.depth_m[hit])  # range along the ray, not z
    np.testing.assert_allclose(f.range_m[hit] * f.rays_cam[hit][:, 2], f.depth_m[hit], rtol=1e-5)
    np.testing.assert_allclose(f.normals_cam[hit], np.tile([0, 0, -1.0], (hit.sum(), 1)), atol=1e-6)
    assert set(np.unique(f.instance)) == {0, 3} and set(np.unique(f.class_id)) == {0, 2}
    assert np.isinf(f.range_m[~hit]).all() and (f.normals_cam[~hit] == 0).all()
    np.testing.assert_array_equal(f.full_masks[3], hit)
    # the cube spans x in [-0.5, 0.5] at z = 4.5: columns with centre inside u in 40 +- 80 * 0.5 / 4.5
    cols = np.flatnonzero(hit[30])
    assert cols[0] == int(np.ceil(40 - 80 / 9 - 0.5)) and cols[-1] == int(np.floor(40 + 80 / 9 - 0.5))


def test_a_render_without_normals_has_the_same_depth_and_labels() -> None:
    r = RaycastRenderer([_mesh(_cube(1.0, (0, 0, 0)), 3, 2), _mesh(_cube(0.5, (0.6, -1.0, 0.2)), 5, 1)], CAM)
    T = _look_at(np.array([1.5, -5.0, 1.0]), np.zeros(3))
    full, lean = r.render(T, with_full_masks=False), r.render(T, with_full_masks=False, with_normals=False)
    for name in ("depth_m", "range_m", "instance", "class_id"):
        np.testing.assert_array_equal(getattr(lean, name), getattr(full, name))
    assert set(np.unique(lean.instance)) == {0, 3, 5}
    assert (lean.normals_cam == 0).all() and (np.abs(full.normals_cam).sum(-1) > 0.5).sum() > 100


def test_full_mask_sees_through_occluders_and_background_gets_no_mask() -> None:
    front = _cube(0.6, (0, -1.0, 0))
    back = _cube(1.0, (0, 1.0, 0))
    ground = trimesh.creation.box(extents=(20, 20, 0.1))
    ground.apply_translation((0, 0, -1))
    r = RaycastRenderer([_mesh(front, 1, 1), _mesh(back, 2, 1), _mesh(ground, 0, 0)], CAM)
    f = r.render(_look_at(np.array([0.0, -6.0, 0.2]), np.array([0.0, 0.0, 0.0])))
    visible_back = f.instance == 2
    assert set(f.full_masks) == {1, 2}  # the ground (instance 0) has no mask
    assert f.full_masks[2].sum() > visible_back.sum() > 0
    assert np.all(f.full_masks[2][visible_back])
    assert np.all(f.full_masks[1] == (f.instance == 1))  # nothing in front of the front cube


@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    az=st.floats(0, 2 * np.pi), el=st.floats(-1.4, 1.4), dist=st.floats(2.0, 50.0),
    offset=st.sampled_from([0.0, 1e3, 5e6]),
)
def test_back_projected_depth_lies_on_the_cube(az: float, el: float, dist: float, offset: float) -> None:
    """From any viewpoint (also far from the origin), depth back-projects onto the cube surface."""
    c = np.array([offset, -offset, offset / 2])
    cube = _cube(1.0, tuple(c))
    r = RaycastRenderer([_mesh(cube, 1, 1)], CAM)
    eye = c + dist * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    T = _look_at(eye, c)
    f = r.render(T, with_full_masks=False)
    hit = f.depth_m > 0
    assert hit.any() and np.isfinite(f.depth_m).all() and np.isfinite(f.normals_cam).all()
    vv, uu = np.nonzero(hit)
    z = f.depth_m[hit].astype(np.float64)
    p_cam = np.stack([(uu + 0.5 - 40.0) / 80.0 * z, (vv + 0.5 - 30.0) / 80.0 * z, z], axis=1)
    p = T.apply(p_cam) - c
    # Open3D casts in float32 but relative to the scene centre: the error scales with the viewing
    # distance only, not with the 5e6 m world offset
    tol = 2e-6 * dist + 1e-6
    np.testing.assert_allclose(np.abs(p).max(axis=1), 0.5, atol=tol)


def test_grazing_view_of_a_plane_has_no_nan() -> None:
    plane = trimesh.Trimesh([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], [[0, 1, 2], [0, 2, 3]])
    r = RaycastRenderer([_mesh(plane, 1, 1)], CAM)
    T = _look_at(np.array([0.0, -8.0, 1e-4]), np.array([0.0, 0.0, 1e-4]))  # eye just above the plane
    f = r.render(T)
    for a in (f.depth_m, f.range_m[np.isfinite(f.range_m)], f.normals_cam):
        assert not np.isnan(a).any()
    assert (f.depth_m >= 0).all()


def test_bad_mesh_lists_raise_input_error() -> None:
    with pytest.raises(InputError, match="empty"):
        RaycastRenderer([], CAM)
    cube = _cube(1.0, (0, 0, 0))
    with pytest.raises(InputError, match="instance id 1"):
        RaycastRenderer([_mesh(cube, 1, 1), _mesh(cube, 1, 2)], CAM)


@pytest.mark.parametrize("k1", [0.0, -0.3, 0.3])
def test_full_masks_of_a_distorted_lens_are_not_cropped(k1: float) -> None:
    """With per-pixel rays of a radially distorted lens (an SfM camera), a part near the image's corner has the same
    full mask as when it alone is cast over the whole frame: the box each mask is cast in covers where the lens puts
    the part, not where a pinhole would (a pincushion lens puts it further out)."""
    from cadalign.raycast.core import pixel_rays_cam

    rays = pixel_rays_cam(CAM)
    r2 = rays[..., 0] ** 2 + rays[..., 1] ** 2
    rays = rays.copy()
    rays[..., :2] /= (1 + k1 * r2)[..., None]  # pixel radius r_d sees the ray of pinhole radius ~ r_d / (1 + k1 r_d^2)
    T = _look_at(np.array([0.0, -5.0, 0.0]), np.zeros(3))
    corner = _cube(0.5, (1.9, 0.0, 1.3))  # near the top-right corner of the view
    centre = _cube(0.6, (0.0, 0.0, 0.0))
    r = RaycastRenderer([_mesh(corner, 1, 1), _mesh(centre, 2, 1)], CAM, rays_cam=rays)
    f = r.render(T)
    alone = RaycastRenderer([_mesh(corner, 1, 1)], CAM, rays_cam=rays).render(T, with_full_masks=False)
    assert (alone.instance == 1).sum() > 20
    np.testing.assert_array_equal(f.full_masks[1], alone.instance == 1)

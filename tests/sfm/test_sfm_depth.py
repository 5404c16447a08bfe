"""SfM depth maps: exact projection of observed points, nearest wins, invalid = 0."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from cadalign.sfm.depth import frame_points, sparse_depth, splat_depth


def test_splat_depth_exact_pixel_and_nearest_wins():
    uv = np.array([[2.7, 1.2], [2.1, 1.9], [0.0, 0.0], [3.999, 2.999], [-0.1, 1.0], [4.0, 1.0], [1.5, 1.5]])
    z = np.array([5.0, 3.0, 7.0, 2.0, 1.0, 1.0, -1.0])
    d = splat_depth(uv, z, width=4, height=3)
    assert d.dtype == np.float32 and d.shape == (3, 4)
    expected = np.zeros((3, 4), np.float32)
    expected[1, 2] = 3.0  # two points in pixel (2, 1): the nearer one
    expected[0, 0] = 7.0  # pixel (0, 0) covers [0, 1)^2
    expected[2, 3] = 2.0
    np.testing.assert_array_equal(d, expected)  # outside or behind the camera: dropped


def test_splat_depth_radius_fills_a_square():
    d = splat_depth(np.array([[5.5, 5.5]]), np.array([2.0]), 10, 10, radius_px=1)
    assert (d > 0).sum() == 9 and np.all(d[4:7, 4:7] == 2.0)
    assert np.all(splat_depth(np.zeros((0, 2)), np.zeros(0), 5, 4) == 0)
    with pytest.raises(ValueError):
        splat_depth(np.zeros((2, 2)), np.zeros(3), 5, 4)


def _one_image_model(points_cam: np.ndarray, observed: list[bool]) -> pycolmap.Reconstruction:
    """One PINHOLE camera (fx 100, fy 110, cx 20, cy 15, 40x30) at a known pose observing some points."""
    cam = pycolmap.Camera.create_from_model_name(1, "PINHOLE", 100.0, 40, 30)
    cam.params = [100.0, 110.0, 20.0, 15.0]
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(cam)
    R = pycolmap.Rotation3d(np.array([0.0, 0.0, np.sin(0.15), np.cos(0.15)]))  # xyzw, 17.2 deg about z
    cam_from_world = pycolmap.Rigid3d(R, np.array([0.3, -0.1, 0.5]))
    world_pts = (points_cam - cam_from_world.translation) @ cam_from_world.rotation.matrix()
    kps = cam.img_from_cam(points_cam)
    rec.add_image_with_trivial_frame(pycolmap.Image(name="a.png", keypoints=kps, camera_id=1, image_id=1),
                                     cam_from_world)
    for k, (xyz, obs) in enumerate(zip(world_pts, observed, strict=True)):
        track = pycolmap.Track()
        if obs:
            track.add_element(1, k)
        pid = rec.add_point3D(xyz, track)
        if obs:
            rec.images[1].set_point3D_for_point2D(k, pid)
    return rec


def test_sparse_depth_on_a_hand_made_model():
    pts = np.array([[0.15, -0.2, 2.0], [0.0, 0.0, 4.0], [0.01, 0.01, 3.0]])
    rec = _one_image_model(pts, [True, True, False])
    d = sparse_depth(rec, 1, min_track_length=1)
    # by hand: u = 100 * 0.15 / 2 + 20 = 27.5 -> column 27; v = 110 * -0.2 / 2 + 15 = 4.0 -> row 4
    assert d[4, 27] == pytest.approx(2.0)
    assert d[15, 20] == pytest.approx(4.0)  # the principal point
    assert (d > 0).sum() == 2  # the unobserved point is not drawn
    assert sparse_depth(rec, 1, min_track_length=2).max() == 0  # tracks of length 1 are skipped


def test_sparse_depth_on_synthesized_dataset():
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_frames_per_rig, opts.num_points3D = 1, 4, 60
    opts.camera_width, opts.camera_height = 64, 48
    opts.camera_model_id = pycolmap.CameraModelId.PINHOLE
    opts.camera_params = [70.0, 70.0, 32.0, 24.0]
    pycolmap.set_random_seed(0)
    rec = pycolmap.synthesize_dataset(opts)
    for image_id in rec.reg_image_ids():
        uv, xyz = frame_points(rec, image_id)
        d = sparse_depth(rec, image_id)
        assert len(uv) > 10
        ij = np.floor(uv).astype(int)
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < 64) & (ij[:, 1] >= 0) & (ij[:, 1] < 48)
        for (i, j), z in zip(ij[inside], xyz[inside, 2], strict=True):
            assert 0 < d[j, i] <= z + 1e-5  # the point or a nearer one in the same pixel
        # observations of the synthetic model are exact projections: uv equals the keypoints
        im = rec.images[image_id]
        obs = np.array([p.xy for p in im.points2D if p.has_point3D()])
        np.testing.assert_allclose(np.sort(uv, axis=0), np.sort(obs, axis=0), atol=1e-6)

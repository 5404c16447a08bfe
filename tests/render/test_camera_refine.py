"""CAD-anchored camera refinement: recovers the focal length and poses of a perturbed SfM model, flags
frames it cannot check, and leaves the input model unchanged."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from cadalign.align.camera_refine import CameraRefineConfig, refine_cameras
from cadalign.types import Sim3

F = 300.0


def _cad_through(points: np.ndarray, size: float = 0.002) -> tuple[np.ndarray, np.ndarray]:
    """A 'CAD' made of tiny tetrahedra centred on ``points``: the surface passes within ``size`` of each."""
    tet = trimesh.creation.icosphere(subdivisions=0, radius=size)
    verts = np.concatenate([tet.vertices + p for p in points])
    faces = np.concatenate([tet.faces + k * len(tet.vertices) for k in range(len(points))])
    return verts, faces


@pytest.fixture()
def scene() -> tuple[pycolmap.Reconstruction, dict[int, np.ndarray], np.ndarray, np.ndarray]:
    opts = pycolmap.SyntheticDatasetOptions()
    opts.num_rigs, opts.num_frames_per_rig, opts.num_points3D = 1, 6, 300
    opts.camera_width, opts.camera_height = 320, 240
    opts.camera_model_id = pycolmap.CameraModelId.SIMPLE_RADIAL
    opts.camera_params = [F, 160.0, 120.0, 0.0]
    pycolmap.set_random_seed(5)
    rec = pycolmap.synthesize_dataset(opts)
    truth = {im.image_id: np.asarray(im.projection_center()) for im in rec.images.values()}
    pts = np.array([p.xyz for p in rec.points3D.values()])
    verts, faces = _cad_through(pts)
    return rec, truth, verts, faces


def _perturb(rec: pycolmap.Reconstruction, rng: np.random.Generator) -> None:
    """What SfM gets wrong: focal +1 %, points off by ~5 mm, cameras turned/moved slightly."""
    cam = next(iter(rec.cameras.values()))
    cam.params = [F * 1.01, 160.0, 120.0, 0.0]
    for p in rec.points3D.values():
        p.xyz = p.xyz + rng.normal(0, 0.005, 3)
    for im in rec.images.values():
        fr = rec.frames[im.frame_id]
        d = pycolmap.Rigid3d(pycolmap.Rotation3d(Rotation.from_rotvec(rng.normal(0, 0.002, 3)).as_quat()),
                             rng.normal(0, 0.01, 3))
        fr.rig_from_world = d * im.cam_from_world()


def test_anchored_adjustment_recovers_focal_and_poses(scene) -> None:
    rec, truth, verts, faces = scene
    _perturb(rec, np.random.default_rng(0))
    before_focal = float(rec.cameras[1].params[0])
    err_before = max(np.linalg.norm(np.asarray(im.projection_center()) - truth[im.image_id])
                     for im in rec.images.values())
    res = refine_cameras(rec, Sim3.identity(), verts, faces, CameraRefineConfig(snap_max_m=0.03, min_inliers=15))
    assert float(rec.cameras[1].params[0]) == before_focal  # the input model is left unchanged
    focal = res.summary["cameras"]["1"]["params_after"][0]
    assert abs(focal - F) / F < 2e-3 < abs(before_focal - F) / F
    assert res.summary["points_on_cad"] == res.summary["points"] == 300
    assert res.summary["reprojection_px"]["after"] < 0.5 * res.summary["reprojection_px"]["before"]
    err_after = 0.0
    for im in rec.images.values():
        r = res.frames[im.name]
        assert r.verified and r.n_inliers >= 15
        err_after = max(err_after, float(np.linalg.norm(r.T_world_from_cam.t - truth[im.image_id])))
    assert err_after < 0.3 * err_before


def test_frames_without_points_on_the_cad_are_not_verified_and_keep_their_pose(scene) -> None:
    rec, _, verts, faces = scene
    far = verts + np.array([50.0, 0.0, 0.0])  # the CAD is elsewhere: no SfM point lies on it
    res = refine_cameras(rec, Sim3.identity(), far, faces, CameraRefineConfig())
    assert res.summary["points_on_cad"] == 0
    for im in rec.images.values():
        r = res.frames[im.name]
        assert not r.verified and r.n_pairs == 0
        np.testing.assert_allclose(r.T_world_from_cam.t, im.projection_center(), atol=1e-9)

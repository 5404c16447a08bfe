"""SfM-vs-ground-truth metrics on exact synthetic camera sets."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadalign.errors import InputError
from cadalign.evaluate.sfm import depth_errors, median_scene_distance, pose_errors
from cadalign.types import Sim3


def _orbit(n: int = 12, radius: float = 10.0) -> dict:
    """cameras.json of n cameras on a circle looking at the origin."""
    frames = {}
    for k in range(n):
        a = 2 * np.pi * k / n
        C = np.array([radius * np.cos(a), radius * np.sin(a), 3.0 + 0.2 * np.sin(3 * a)])
        z = -C / np.linalg.norm(C)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in world
        frames[f"{k:06d}.png"] = {"K": [100.0, 0, 32, 0, 100.0, 24, 0, 0, 1], "width": 64, "height": 48,
                                  "R_cam_from_world": R.ravel().tolist(), "t_cam_from_world_m": (-R @ C).tolist()}
    return {"frames": frames}


def _transform(cams: dict, S: Sim3) -> dict:
    """The same cameras in a frame where world points are ``S^-1`` of the original (an SfM gauge)."""
    out = {}
    for name, f in cams["frames"].items():
        R = np.reshape(f["R_cam_from_world"], (3, 3))
        C = -R.T @ np.array(f["t_cam_from_world_m"])
        C2 = S.inverse().apply(C)
        R2 = R @ S.R
        out[name] = {**f, "R_cam_from_world": R2.ravel().tolist(), "t_cam_from_world_m": (-R2 @ C2).tolist()}
    return {"frames": out}


def test_pose_errors_zero_for_an_exact_similarity():
    gt = _orbit()
    S = Sim3(0.37, Rotation.from_rotvec([0.3, -1.0, 0.5]).as_matrix(), np.array([4.0, -2.0, 1.0]))
    est = _transform(gt, S)
    pe = pose_errors(est, gt)
    assert pe.gt_from_sfm.s == pytest.approx(0.37, rel=1e-9)
    assert np.max(pe.rot_err_deg) < 1e-6 and np.max(pe.centre_err_m) < 1e-8
    assert pe.names == sorted(gt["frames"])


def test_pose_errors_sees_a_rotated_camera_and_missing_frames():
    gt = _orbit()
    est = _transform(gt, Sim3(2.0))
    name = "000003.png"
    R = np.reshape(est["frames"][name]["R_cam_from_world"], (3, 3))
    C = -R.T @ np.array(est["frames"][name]["t_cam_from_world_m"])
    R = Rotation.from_rotvec([0.0, np.radians(1.0), 0.0]).as_matrix() @ R  # 1 degree off, same centre
    est["frames"][name].update(R_cam_from_world=R.ravel().tolist(), t_cam_from_world_m=(-R @ C).tolist())
    del est["frames"]["000007.png"]
    pe = pose_errors(est, gt)
    assert len(pe.names) == 11
    assert pe.rot_err_deg[pe.names.index(name)] == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(InputError, match="need 3"):
        pose_errors({"frames": dict(list(est["frames"].items())[:2])}, gt)


def test_depth_errors_and_scene_distance(tmp_path):
    gt = np.full((4, 5), 8.0)
    gt[0] = 0.0  # no surface
    d = np.zeros((4, 5), np.float32)
    d[1, 1], d[2, 2], d[0, 0] = 4.0, 4.4, 3.0  # SfM units; true scale 2 m per unit
    (tmp_path / "depth").mkdir()
    np.save(tmp_path / "depth" / "000000.npy", d)
    r = depth_errors(tmp_path / "depth", {"000000.png": gt}, scale=2.0)
    assert r["coverage_mean"] == pytest.approx(3 / 20)
    assert r["pixels_compared"] == 2
    assert r["abs_rel"] == pytest.approx((0.0 + 0.8 / 8.0) / 2)
    assert median_scene_distance({"a": gt, "b": np.array([[0.0, 2.0]])}) == 8.0

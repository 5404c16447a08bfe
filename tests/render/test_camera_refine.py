"""Per-frame camera refinement against the CAD: recovers a perturbed pose, flags unusable frames."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from cadalign.render.camera_refine import CameraRefineConfig, _refine_one
from cadalign.types import Rigid3

F = 460.0


def _views(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, Rigid3]:
    T_world_from_cam = Rigid3(Rotation.from_rotvec([0.1, -0.2, 0.05]).as_matrix(), np.array([0.5, -0.3, -8.0]))
    X_cam = np.c_[rng.uniform(-3, 3, (n, 2)), rng.uniform(6, 10, n)]
    X = T_world_from_cam.apply(X_cam)
    xy = X_cam[:, :2] / X_cam[:, 2:] + rng.normal(0, 0.3 / F, (n, 2))  # 0.3 px keypoint noise
    return xy, X, T_world_from_cam


def test_refinement_recovers_a_perturbed_pose_and_rejects_outliers() -> None:
    rng = np.random.default_rng(0)
    xy, X, truth = _views(rng, 200)
    xy[:20] += rng.uniform(-0.05, 0.05, (20, 2))  # 10 % gross outliers (~20 px)
    T0 = Rigid3(Rotation.from_rotvec([0.0, 0.004, 0.0]).as_matrix() @ truth.R, truth.t + [0.04, -0.03, 0.05])
    r = _refine_one(xy, X, F, T0, CameraRefineConfig())
    assert r.verified and 150 <= r.n_inliers <= 185
    assert np.linalg.norm(r.T_world_from_cam.t - truth.t) < 0.01 < np.linalg.norm(T0.t - truth.t)
    assert r.rms_px < 1.0


def test_too_few_pairs_or_a_big_jump_is_not_verified() -> None:
    rng = np.random.default_rng(1)
    xy, X, truth = _views(rng, 10)
    r = _refine_one(xy, X, F, truth, CameraRefineConfig())
    assert not r.verified and r.T_world_from_cam is truth
    xy, X, truth = _views(rng, 200)
    far = Rigid3(truth.R, truth.t + [0.2, 0.0, 0.0])
    r = _refine_one(xy, X, F, far, CameraRefineConfig(max_shift_m=0.1))
    assert not r.verified and r.T_world_from_cam is far  # the SfM pose is kept, the frame flagged

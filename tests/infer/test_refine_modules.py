"""The refinement package (cadalign.infer.refine) re-exports the public names of its modules."""

from __future__ import annotations

import numpy as np

from cadalign.infer import refine
from cadalign.infer.refine import contour_fit, depth_icp, refine_math


def test_refine_reexports_the_moved_names():
    assert refine.refine_silhouette is contour_fit.refine_silhouette
    assert refine.SignedDistance is contour_fit.SignedDistance
    assert refine.silhouette_iou is contour_fit.silhouette_iou
    assert refine.refine_depth_icp is depth_icp.refine_depth_icp
    assert refine.masked_depth_points is depth_icp.masked_depth_points
    assert refine.depth_along_ray is depth_icp.depth_along_ray
    assert refine.depth_fit is depth_icp.depth_fit
    assert refine.ICP_DAMPING == depth_icp.ICP_DAMPING == 1e-6
    assert refine.apply_twist is refine_math.apply_twist
    assert set(refine.__all__) <= set(dir(refine))


def test_huber_weights_and_damped_solve_on_a_hand_case():
    w = refine_math.huber_weights(np.array([0.5, -2.0, 4.0]), 1.0)
    np.testing.assert_allclose(w, [1.0, 0.5, 0.25])
    J, r = np.eye(6), np.arange(6.0)  # minimise |r + xi|^2: xi = -r (no damping)
    np.testing.assert_allclose(refine_math.solve_step(J, r, np.ones(6), 0.0), -r)
    assert refine_math.solve_step(J[:5], r[:5], np.ones(5), 0.0) is None  # under-determined
    big = refine_math.clamp_step(np.array([1.0, 0, 0, 0, 0, 4.0]), diameter_m=2.0)
    np.testing.assert_allclose(big, [0.2, 0, 0, 0, 0, 0.5])


def test_pick_fit_breaks_ties_by_the_turn_from_the_start() -> None:
    from cadalign.geometry.rotations import axis_angle_to_matrix
    from cadalign.types import Rigid3

    def turned(deg: float) -> Rigid3:
        return Rigid3(axis_angle_to_matrix(np.array([0.0, 0.0, np.radians(deg)])), np.zeros(3))

    poses = [turned(170.0), turned(5.0), turned(0.0)]
    fits = [0.0040, 0.0042, 0.0100]
    start = turned(0.0)
    assert refine.pick_fit(fits, poses, start, 0.0) == 0  # the best fit outright
    assert refine.pick_fit(fits, poses, start, 0.0005) == 1  # a tie: the one nearer the start
    assert refine.pick_fit(fits, poses, start, 0.01) == 2
    assert refine.pick_fit(fits[:1], poses[:1], start, 1.0) == 0
    assert refine.pick_fit([0.005, 0.004, 0.004], poses, start, 0.0) == 1  # equal fits: the first

"""Half-turn check (RefineConfig.half_turn_check): the ball valve's off-centre lever decides between a pose and
its half turn about z, from a view at the default scene's distances (10 m, f = 457 px)."""

from __future__ import annotations

import numpy as np
import pytest
from infer_testdata import render_close_view

from cadalign.cad.model import CadModel
from cadalign.cad.procedural import make_part
from cadalign.cad.symmetry import Symmetry
from cadalign.infer.config import RefineConfig
from cadalign.infer.model_geom import ModelGeometry, render_depth, render_silhouette
from cadalign.infer.refine import refine
from cadalign.infer.refine.half_turn import half_turned, needs_half_turn_check, pick_half_turn, view_disagreement
from cadalign.metrics.pose import rotation_error_deg, translation_error_m
from cadalign.types import Rigid3

EYE = np.array([6.0, 7.5, 3.0])  # ~10 m from the valve, looking down a little
CFG = RefineConfig(half_turn_check=True)


@pytest.fixture(scope="module")
def ball_valve():
    mesh = make_part("valve_b")
    model = CadModel("valve_b", np.asarray(mesh.vertices), np.asarray(mesh.faces, dtype=np.int64))
    view = render_close_view(model, EYE, size=(160, 120), f=457.0)
    depth = np.where(view.mask, view.depth_m, 14.0)  # a wall 14 m away behind the valve
    return ModelGeometry.from_cad(model), view, depth


def test_render_depth_matches_the_renderer(ball_valve) -> None:
    geom, view, _ = ball_valve
    z = render_depth(geom, view.T_cam_from_obj, view.camera.K, view.mask.shape)
    assert np.array_equal(np.isfinite(z), view.mask)
    assert np.array_equal(render_silhouette(geom, view.T_cam_from_obj, view.camera.K, view.mask.shape), view.mask)
    np.testing.assert_allclose(z[view.mask], view.depth_m[view.mask], atol=1e-3)


@pytest.mark.parametrize("background", ["wall", "water", "no depth"])
def test_the_lever_tells_a_pose_from_its_half_turn(ball_valve, background: str) -> None:
    geom, view, depth = ball_valve
    T, K = view.T_cam_from_obj, view.camera.K
    d = {"wall": depth, "water": np.where(view.mask, view.depth_m, 0.0), "no depth": None}[background]
    best, (a, b) = pick_half_turn(geom, half_turned(T), T, K, view.mask, d, 0.04, 3)
    # the lever's pixels: measured 36 with the wall or the silhouettes, 19 with water (no see-through pixels)
    assert best is T and b == 0 and a >= 10
    best, _ = pick_half_turn(geom, T, half_turned(T), K, view.mask, d, 0.04, 3)
    assert best is T


def test_refine_turns_a_flipped_valve_back(ball_valve) -> None:
    geom, view, depth = ball_valve
    T_gt, K = view.T_cam_from_obj, view.camera.K
    T0 = half_turned(Rigid3(T_gt.R, T_gt.t + [0.02, -0.01, 0.05]))
    without = refine(geom, T0, K, view.mask, RefineConfig(), depth).T_cam_from_obj
    res = refine(geom, T0, K, view.mask, CFG, depth)
    assert rotation_error_deg(without.R, T_gt.R) > 170
    assert res.iterations["half_turn"] == 1
    assert rotation_error_deg(res.T_cam_from_obj.R, T_gt.R) < 2
    assert translation_error_m(res.T_cam_from_obj.t, T_gt.t) < 0.02
    kept = refine(geom, T_gt, K, view.mask, CFG, depth)  # the true pose stays
    assert kept.iterations["half_turn"] == 0 and rotation_error_deg(kept.T_cam_from_obj.R, T_gt.R) < 2


def test_only_parts_without_a_z_turn_symmetry_are_checked(ball_valve) -> None:
    geom, view, depth = ball_valve
    half = Symmetry.cyclic((0.0, 0.0, 1.0), 2)
    assert needs_half_turn_check(None) and needs_half_turn_check(Symmetry.none())
    assert not needs_half_turn_check(half)
    assert not needs_half_turn_check(Symmetry.continuous((0.0, 0.0, 1.0)))
    res = refine(geom, view.T_cam_from_obj, view.camera.K, view.mask, CFG, depth, symmetry=half)
    assert "half_turn" not in res.iterations
    off = refine(geom, view.T_cam_from_obj, view.camera.K, view.mask, RefineConfig(), depth)
    assert "half_turn" not in off.iterations


def test_occluders_and_missing_depth_do_not_count(ball_valve) -> None:
    geom, view, depth = ball_valve
    T, K = view.T_cam_from_obj, view.camera.K
    win = (0, 0, view.mask.shape[1], view.mask.shape[0])
    in_front = np.where(view.mask, view.depth_m - 1.0, 14.0)  # something 1 m in front covers the valve
    assert view_disagreement(geom, T, K, view.mask, in_front, 0.04, win) == 0
    assert view_disagreement(geom, T, K, view.mask, np.zeros_like(depth), 0.04, win) == 0
    assert view_disagreement(geom, T, K, view.mask, depth, 0.04, (5, 5, 5, 9)) == 0  # empty window


def test_the_band_forgives_a_pose_a_few_degrees_off(ball_valve) -> None:
    """A pose 6 deg off in yaw is a pixel off all round; only the band keeps it ahead of the exact wrong half turn."""
    from cadalign.geometry.rotations import axis_angle_to_matrix

    geom, view, depth = ball_valve
    T, K = view.T_cam_from_obj, view.camera.K
    T_off = Rigid3(T.R @ axis_angle_to_matrix(np.array([0.0, 0.0, np.radians(6.0)])), T.t)
    wrong = half_turned(T)
    best, (a, b) = pick_half_turn(geom, T_off, wrong, K, view.mask, depth, 0.04, 3, band_px=1.5)
    assert best is T_off and b >= a + 10  # measured 0 vs 22 px; without the band 59 vs 36 (the wrong turn wins)


def test_unfitted_poses_are_not_compared(ball_valve) -> None:
    """With no refinement run (mask below min_mask_px, no depth) the detector's pose stays as it is."""
    geom, view, _ = ball_valve
    T0 = half_turned(view.T_cam_from_obj)
    cfg = RefineConfig(half_turn_check=True, min_mask_px=10_000)
    res = refine(geom, T0, view.camera.K, view.mask, cfg)
    assert res.T_cam_from_obj is T0 and "half_turn" not in res.iterations

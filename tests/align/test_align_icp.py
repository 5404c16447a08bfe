"""Sim(3) ICP with the scale guard, the known scale-collapse failure, and the point-to-plane refinement."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from align_testdata import make_cloud, sim3_errors
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.align import PRESETS, PointToPlaneConfig, Sim3ICPConfig, align, refine_point_to_plane, sim3_icp
from cadalign.align.icp import _guard_scale, subsample
from cadalign.geometry import axis_angle_to_matrix, random_rotation
from cadalign.types import Sim3


def _perturb(rot_rad: float, trans_m: float, scale: float, seed: int = 0) -> Sim3:
    """A world-frame perturbation: rotation by ``rot_rad`` about a random axis, translation of ``trans_m``."""
    rng = np.random.default_rng(seed)
    axis, direction = rng.normal(size=3), rng.normal(size=3)
    axis, direction = axis / np.linalg.norm(axis), direction / np.linalg.norm(direction)
    return Sim3(scale, axis_angle_to_matrix(rot_rad * axis), trans_m * direction)


def test_icp_from_perturbed_start_recovers(small_cloud, surface):
    init = _perturb(np.radians(3.0), 0.4, 1.08) @ small_cloud.cad_from_sfm
    T, history = sim3_icp(small_cloud.points_sfm, surface, init, Sim3ICPConfig())
    rot, trans, scale = sim3_errors(T, small_cloud.cad_from_sfm, small_cloud.points_sfm)
    assert rot < 0.05 and trans < 0.005 and scale < 5e-4
    assert [h.level for h in history] == sorted(h.level for h in history)  # coarse to fine
    dists = [h.max_dist_m for h in history]
    assert dists == sorted(dists, reverse=True)


@settings(max_examples=6, deadline=None, derandomize=True)
@given(
    log_scale=st.floats(np.log(0.05), np.log(20.0)),
    seed=st.integers(0, 2**16),
    rot_deg=st.floats(0.0, 4.0),
    trans_m=st.floats(0.0, 0.4),
    dscale=st.floats(0.92, 1.08),
)
def test_icp_recovers_any_sim3_from_a_nearby_start(small_cloud, surface, log_scale, seed, rot_deg, trans_m, dscale):
    rng = np.random.default_rng(seed)
    sfm_from_cad = Sim3(float(np.exp(log_scale)), random_rotation(rng), rng.uniform(-100, 100, 3))
    pts = sfm_from_cad.apply(small_cloud.points_world_m)
    gt = sfm_from_cad.inverse()
    init = _perturb(np.radians(rot_deg), trans_m, dscale, seed) @ gt
    T, _ = sim3_icp(pts, surface, init, Sim3ICPConfig())
    T, _ = refine_point_to_plane(pts, surface, T, PointToPlaneConfig())
    rot, trans, scale = sim3_errors(T, gt, pts)
    assert rot < 0.1 and trans < 0.01 and scale < 1e-3


@pytest.fixture(scope="module")
def cluttered():
    """Heavy seabed clutter: 60 % of the cloud on a 40 x 40 m seabed with no CAD counterpart."""
    return make_cloud(5, n_structure=3000, clutter_frac=0.6, seabed_half_m=20.0)


# One large correspondence distance (half the CAD diameter): every seabed point pairs with the CAD.
LARGE = (0.5,)


def test_unguarded_icp_scale_collapses_with_clutter(cluttered, surface):
    """The known failure: without the guard, trimming and a shrinking schedule, the scale runs away."""
    init = _perturb(np.radians(1.7), 0.35, 0.95, seed=1) @ cluttered.cad_from_sfm
    cfg = Sim3ICPConfig(scale_guard=False, trim_keep=1.0, corr_dist_schedule_rel=LARGE, iters_per_level=40,
                        point_to_plane_targets=False)
    T, history = sim3_icp(cluttered.points_sfm, surface, init, cfg)
    assert T.s / cluttered.cad_from_sfm.s < 0.5
    assert not any(h.scale_clamped for h in history)


def test_guard_bounds_the_scale_under_the_same_conditions(cluttered, surface):
    """Same single large distance and no trimming, guard on: the scale stops at its bound, never below."""
    init = _perturb(np.radians(1.7), 0.35, 0.95, seed=1) @ cluttered.cad_from_sfm
    cfg = Sim3ICPConfig(trim_keep=1.0, corr_dist_schedule_rel=LARGE, iters_per_level=40)
    T, history = sim3_icp(cluttered.points_sfm, surface, init, cfg)
    lo = init.s / cfg.scale_range
    assert T.s >= lo * (1 - 1e-9)
    assert any(h.scale_clamped for h in history)
    steps = np.array([init.s] + [h.scale for h in history])
    assert np.all(np.abs(np.log(steps[1:] / steps[:-1])) <= np.log(1 + cfg.max_scale_step) + 1e-12)


def test_guarded_icp_recovers_from_a_large_start_distance(cluttered, surface):
    """The full guard (bounded scale, trimming, shrinking schedule) recovers from the same start."""
    init = _perturb(np.radians(1.7), 0.35, 0.95, seed=1) @ cluttered.cad_from_sfm
    cfg = Sim3ICPConfig(corr_dist_schedule_rel=(0.5, 0.06, 0.03, 0.015, 0.008))
    T, _ = sim3_icp(cluttered.points_sfm, surface, init, cfg)
    rot, trans, scale = sim3_errors(T, cluttered.cad_from_sfm, cluttered.points_sfm)
    assert rot < 0.05 and trans < 0.005 and scale < 5e-4


def test_a_run_that_ends_on_the_scale_bound_fails_the_gate(cluttered, parts):
    """If ICP is pinned to the guard bound, the scale gate reports it instead of returning it."""
    from cadalign.align import AlignmentGateError

    init = _perturb(np.radians(1.7), 0.35, 0.95, seed=1) @ cluttered.cad_from_sfm
    base = PRESETS["fast"]
    cfg = replace(base, icp=replace(base.icp, trim_keep=1.0, corr_dist_schedule_rel=LARGE, iters_per_level=40),
                  refine=replace(base.refine, enabled=False))
    with pytest.raises(AlignmentGateError) as exc:
        align(cluttered.points_sfm, parts, cfg, prior=init)
    assert "scale_change_vs_coarse" in exc.value.failed


@settings(max_examples=50, deadline=None, derandomize=True)
@given(step=st.floats(1e-6, 1e6), s_now=st.floats(0.81, 1.24))
def test_guard_keeps_both_bounds(step, s_now):
    """From inside the allowed range, any proposed step ends within the step bound and the range."""
    cfg = Sim3ICPConfig()
    s_step, clamped = _guard_scale(Sim3(step), s_now, 1.0, cfg)
    assert abs(np.log(s_step)) <= np.log(1 + cfg.max_scale_step) + 1e-12
    assert 1 / cfg.scale_range - 1e-12 <= s_now * s_step <= cfg.scale_range + 1e-12
    assert clamped == (not np.isclose(s_step, step, rtol=1e-12, atol=0))


def test_guard_off_passes_the_step_through():
    s_step, clamped = _guard_scale(Sim3(0.3), 1.0, 1.0, Sim3ICPConfig(scale_guard=False))
    assert s_step == 0.3 and not clamped


def test_refine_keeps_the_scale_and_improves(small_cloud, surface):
    init = _perturb(np.radians(0.3), 0.03, 1.0) @ small_cloud.cad_from_sfm
    T, step = refine_point_to_plane(small_cloud.points_sfm, surface, init, PointToPlaneConfig())
    assert T.s == pytest.approx(init.s, rel=1e-12)
    assert step is not None and step.stage == "refine"
    before = sim3_errors(init, small_cloud.cad_from_sfm, small_cloud.points_sfm)
    after = sim3_errors(T, small_cloud.cad_from_sfm, small_cloud.points_sfm)
    assert after[0] < before[0] / 5 and after[1] < before[1] / 5


def test_refine_without_pairs_returns_the_start(small_cloud, surface):
    far = Sim3(1.0, np.eye(3), np.array([1e3, 0.0, 0.0])) @ small_cloud.cad_from_sfm
    T, step = refine_point_to_plane(small_cloud.points_sfm, surface, far, PointToPlaneConfig())
    assert step is None and np.allclose(T.matrix(), far.matrix())


def test_subsample_is_seeded_and_ordered():
    pts = np.arange(300.0).reshape(100, 3)
    a, b = subsample(pts, 10, 7), subsample(pts, 10, 7)
    assert np.array_equal(a, b) and len(a) == 10
    assert np.all(np.diff(a[:, 0]) > 0)
    assert subsample(pts, 1000, 0) is pts

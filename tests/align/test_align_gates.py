"""Quality gates: wrong units, a wrong CAD, too few points on the structure and a scale prior all raise
an AlignmentError whose message carries the numbers and the likely cause; nothing bad passes silently.

(Near-symmetric structures are a different problem: a turned-around match can pass every gate. The
global registration scores symmetric turns explicitly and reports the runner-up in ``global_scores``.)
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from align_testdata import make_cloud, model_of

from cadalign.align import PRESETS, AlignmentGateError, align, check_gates, measure
from cadalign.align.gates import format_report
from cadalign.cad.procedural import make_part
from cadalign.errors import AlignmentError
from cadalign.types import Rigid3, Sim3

FAST = PRESETS["fast"]
# the size gate off, to show the metric gates catch a unit error on their own
NO_SIZE_GATE = replace(FAST, gates=replace(FAST.gates, cad_size_range_m=(1e-9, 1e9)))


def _scaled_parts(parts, k: float):
    """The structure with every coordinate multiplied by ``k`` (a CAD read in the wrong unit)."""
    return [(m.scaled(k), Rigid3(T.R, T.t * k)) for m, T in parts]


def test_mm_read_as_m_fails_globally_with_a_unit_message(small_cloud, parts):
    """The realistic case: the CAD is 1000x too big and nobody knows; the global path (scale-free) still
    'aligns' it. One scale hypothesis without symmetric turns keeps the test quick."""
    cfg = replace(FAST, global_reg=replace(FAST.global_reg, scale_factors=(1.0,), symmetry_variants=False))
    with pytest.raises(AlignmentError) as exc:
        align(small_cloud.points_sfm, _scaled_parts(parts, 1000.0), cfg)
    err = exc.value
    assert isinstance(err, AlignmentGateError)
    assert {"cad_extent_m", "fitness", "n_inliers"} <= set(err.failed)
    msg = str(err)
    assert "unit" in msg and "millimetres read as metres" in msg
    assert "FAIL cad_extent_m = 1.00" in msg  # the number and its bound are in the report


def test_mm_read_as_m_is_caught_without_the_size_gate(cloud, parts):
    prior = Sim3(1000.0) @ cloud.cad_from_sfm  # even a perfect start cannot make 1.5 cm noise 15 m of fit
    with pytest.raises(AlignmentGateError) as exc:
        align(cloud.points_sfm, _scaled_parts(parts, 1000.0), NO_SIZE_GATE, prior=prior)
    assert "fitness" in exc.value.failed and "unit" in str(exc.value)


def test_m_read_as_mm_fails_with_a_unit_message(cloud, parts):
    with pytest.raises(AlignmentGateError) as exc:
        align(cloud.points_sfm, _scaled_parts(parts, 0.001), FAST, prior=Sim3(0.001) @ cloud.cad_from_sfm)
    assert "cad_extent_m" in exc.value.failed and "unit" in str(exc.value)


def test_m_read_as_mm_is_caught_without_the_size_gate(cloud, parts):
    """A 1000x too small CAD aligns 'perfectly'; the residuals are then implausibly small for SfM."""
    with pytest.raises(AlignmentGateError) as exc:
        align(cloud.points_sfm, _scaled_parts(parts, 0.001), NO_SIZE_GATE, prior=Sim3(0.001) @ cloud.cad_from_sfm)
    assert exc.value.failed == ("inlier_rmse_floor_m",)
    assert "implausibly small" in str(exc.value) and "unit" in str(exc.value)


def test_a_different_cad_fails_the_fitness_gate(cloud):
    """A solid box of the frame's size: its faces even coincide with the frame's outer faces and the
    seabed, yet the points inside the box but off its faces give it away."""
    box = [(model_of(make_part("box", (9.0, 10.0, 6.0)), "box"), Rigid3())]
    with pytest.raises(AlignmentGateError) as exc:
        align(cloud.points_sfm, box, FAST, prior=cloud.cad_from_sfm)
    assert "fitness" in exc.value.failed and "wrong CAD" in str(exc.value)
    assert exc.value.metrics.fitness < FAST.gates.min_fitness - 0.05


def test_too_few_points_on_the_structure(parts):
    sparse = make_cloud(4, n_structure=120, clutter_frac=0.95, outlier_frac=0.02)
    with pytest.raises(AlignmentGateError) as exc:
        align(sparse.points_sfm, parts, FAST, prior=sparse.cad_from_sfm)
    assert {"n_inliers", "inlier_fraction_all"} <= set(exc.value.failed)
    assert "too few" in str(exc.value)


@pytest.mark.parametrize(("ratio", "passes"), [(1.1, True), (2.0, False)])
def test_expected_scale_gate(small_cloud, surface, ratio, passes):
    cfg = replace(FAST, gates=replace(FAST.gates, expected_scale=small_cloud.cad_from_sfm.s * ratio))
    if passes:
        r = align(small_cloud.points_sfm, surface, cfg, prior=small_cloud.cad_from_sfm)
        assert any(g.name == "scale_vs_expected" and g.passed for g in r.gates)
    else:
        with pytest.raises(AlignmentGateError) as exc:
            align(small_cloud.points_sfm, surface, cfg, prior=small_cloud.cad_from_sfm)
        assert exc.value.failed == ("scale_vs_expected",)


def test_good_alignment_passes_every_gate_and_report_says_so(small_cloud, surface):
    T = small_cloud.cad_from_sfm
    m = measure(small_cloud.points_sfm, surface, T, FAST.gates)
    checks = check_gates(m, T, T, surface, FAST.gates)
    assert all(c.passed for c in checks)
    assert m.fitness > 0.9 and 0.01 < m.inlier_rmse_m < 0.02
    report = format_report(checks, m, T, "cloud.ply")
    assert report.startswith("alignment of cloud.ply passed all quality gates")


def test_gate_values_are_never_nan_passes(small_cloud, surface):
    """No points near the CAD: RMSE is inf and must fail, not slip through a NaN comparison."""
    far = Sim3(1.0, np.eye(3), np.array([1e4, 0.0, 0.0])) @ small_cloud.cad_from_sfm
    m = measure(small_cloud.points_sfm, surface, far, FAST.gates)
    checks = {c.name: c for c in check_gates(m, far, far, surface, FAST.gates)}
    assert m.n_inliers == 0 and not checks["inlier_rmse_m"].passed and not checks["inlier_rmse_floor_m"].passed


def test_fitness_counts_the_multi_view_points(small_cloud, surface):
    """Points seen in two images only scatter along their rays: scattered off the surface and marked two-view,
    they leave the fitness as it was; marked as seen in three images they lower it. Too few multi-view points
    to judge by: every point counts."""
    T = small_cloud.cad_from_sfm
    pts = small_cloud.points_sfm
    n = len(pts)
    rng = np.random.default_rng(0)
    # the same points again, moved 8-20 cm off along random directions (in CAD metres, then back to SfM units)
    off = rng.normal(size=(n, 3))
    off *= (rng.uniform(0.08, 0.2, n) / np.linalg.norm(off, axis=1))[:, None]
    scattered = T.inverse().apply(T.apply(pts) + off)
    both = np.concatenate([pts, scattered])
    clean = measure(pts, surface, T, FAST.gates)
    two_view = measure(both, surface, T, FAST.gates, np.r_[np.full(n, 5), np.full(n, 2)])
    three_view = measure(both, surface, T, FAST.gates, np.r_[np.full(n, 5), np.full(n, 3)])
    unknown = measure(both, surface, T, FAST.gates)
    assert two_view.fitness == pytest.approx(clean.fitness) and two_view.n_fitness == clean.n_roi
    assert three_view.fitness < 0.8 * clean.fitness and unknown.fitness == pytest.approx(three_view.fitness)
    assert two_view.n_roi == three_view.n_roi > clean.n_roi  # the other metrics see every point
    few = measure(both, surface, T, replace(FAST.gates, min_inliers=n + 1), np.r_[np.full(n, 5), np.full(n, 2)])
    assert few.fitness == pytest.approx(unknown.fitness)

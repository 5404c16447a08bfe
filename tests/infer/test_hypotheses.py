"""Yaw restarts spread over the yaw range a part's symmetry leaves distinct."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.cad.symmetry import Symmetry
from cadalign.infer.refine.hypotheses import yaw_hypotheses_rad, yaw_period_rad


@pytest.mark.parametrize(("name", "period_deg"), [
    ("none", 360.0), ("discrete_z2", 180.0), ("discrete_z4", 90.0), ("continuous_z", 0.0),
    ("discrete_x2", 360.0), ("discrete_y4", 360.0), ("continuous_x", 360.0),
])
def test_yaw_period_of_named_symmetries(name: str, period_deg: float) -> None:
    assert math.degrees(yaw_period_rad(Symmetry.from_name(name))) == pytest.approx(period_deg, abs=1e-9)
    assert yaw_period_rad(None) == pytest.approx(2 * math.pi)


def test_four_restarts_of_a_half_turn_symmetric_part_are_45_deg_apart() -> None:
    half = Symmetry.from_name("discrete_z2")
    assert [math.degrees(a) for a in yaw_hypotheses_rad(4, half)] == pytest.approx([0.0, 45.0, 90.0, 135.0])
    assert [math.degrees(a) for a in yaw_hypotheses_rad(4, None)] == pytest.approx([0.0, 90.0, 180.0, 270.0])
    assert yaw_hypotheses_rad(4, Symmetry.from_name("continuous_z")) == [0.0]
    assert yaw_hypotheses_rad(1, half) == [0.0]


@settings(max_examples=15, deadline=None)
@given(order=st.integers(2, 8), n=st.integers(1, 6))
def test_cyclic_z_symmetry_restarts_cover_one_period(order: int, n: int) -> None:
    sym = Symmetry.cyclic((0.0, 0.0, 1.0), order, offset_m=(0.1, -0.2, 0.0))
    yaws = yaw_hypotheses_rad(n, sym)
    assert yaw_period_rad(sym) == pytest.approx(2 * math.pi / order)
    assert len(yaws) == n and yaws[0] == 0.0
    assert all(0.0 <= a < 2 * math.pi / order for a in yaws)

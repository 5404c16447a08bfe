"""Pareto front and the "within 5% of the best accuracy at the least time" choice: exact hand cases."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.bench.pareto import accuracy_threshold, pareto_front, plot_pareto, recommend


def test_recommend_higher_is_better_picks_cheapest_within_5pct():
    # best 0.97; threshold 0.9215: 0.95 qualifies at cost 2, 0.92 does not
    assert recommend([1.0, 2.0, 4.0], [0.92, 0.95, 0.97], higher_is_better=True) == 1


def test_recommend_lower_is_better_error():
    # best error 1.00 mm; threshold 1.05: 1.04 at 0.3 s qualifies, 1.06 at 0.1 s does not
    assert recommend([0.1, 0.3, 0.9], [1.06, 1.04, 1.00], higher_is_better=False) == 1


def test_recommend_exact_threshold_is_inside():
    assert accuracy_threshold(0.8, higher_is_better=True) == pytest.approx(0.76)
    assert recommend([1.0, 5.0], [0.76, 0.8], higher_is_better=True) == 0
    assert accuracy_threshold(2.0, higher_is_better=False) == pytest.approx(2.1)


def test_recommend_tie_in_cost_takes_more_accurate_then_first():
    assert recommend([1.0, 1.0, 3.0], [0.95, 0.96, 0.96], higher_is_better=True) == 1
    assert recommend([1.0, 1.0], [0.5, 0.5], higher_is_better=True) == 0


def test_recommend_zero_best_error_only_admits_zero():
    assert recommend([0.1, 1.0], [1e-9, 0.0], higher_is_better=False) == 1


def test_recommend_ignores_non_finite_and_empty():
    assert recommend([1.0, math.nan, 3.0], [0.5, 0.99, 0.6], higher_is_better=True) == 2
    assert recommend([1.0, 2.0], [math.nan, math.inf], higher_is_better=True) is None
    assert recommend([], [], higher_is_better=True) is None


def test_recommend_custom_tolerance_and_errors():
    assert recommend([1.0, 2.0], [0.5, 1.0], higher_is_better=True, tol=0.6) == 0
    with pytest.raises(ValueError, match="differ in length"):
        recommend([1.0], [1.0, 2.0], higher_is_better=True)
    with pytest.raises(ValueError, match="tol"):
        recommend([1.0], [1.0], higher_is_better=True, tol=-0.1)


def test_pareto_front_hand_cases():
    assert pareto_front([1.0, 2.0, 3.0], [0.5, 0.4, 0.9], higher_is_better=True) == [0, 2]
    assert pareto_front([1.0, 2.0, 3.0], [3.0, 2.0, 2.5], higher_is_better=False) == [0, 1]
    # exact duplicates are both kept; a point equal in cost but worse is dropped
    assert pareto_front([1.0, 1.0, 1.0], [0.5, 0.5, 0.4], higher_is_better=True) == [0, 1]
    assert pareto_front([1.0, math.nan], [0.5, 0.9], higher_is_better=True) == [0]


finite = st.floats(min_value=0.0, max_value=1e3, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(finite, finite), min_size=1, max_size=12), st.booleans())
def test_recommended_is_on_front_and_cheapest_within_tolerance(pts, higher):
    costs, accs = [p[0] for p in pts], [p[1] for p in pts]
    i = recommend(costs, accs, higher_is_better=higher)
    best = max(accs) if higher else min(accs)
    thr = accuracy_threshold(best, higher_is_better=higher)
    ok = [j for j in range(len(pts)) if (accs[j] >= thr if higher else accs[j] <= thr)]
    assert i in ok and costs[i] == min(costs[j] for j in ok)
    front = pareto_front(costs, accs, higher_is_better=higher)
    assert i in front
    for j in range(len(pts)):  # every point off the front is dominated by one on it
        if j not in front:
            assert any(costs[f] <= costs[j] and (accs[f] >= accs[j] if higher else accs[f] <= accs[j])
                       for f in front)


def test_plot_pareto_writes_png(tmp_path):
    p = plot_pareto(tmp_path / "p.png", ["a", "b", "c"], [0.01, 0.1, 10.0], [0.5, 0.9, 0.95],
                    higher_is_better=True, cost_label="s", acc_label="IoU", title="t", notes=["k=1", "", "k=3"])
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    empty = plot_pareto(tmp_path / "e.png", ["a"], [math.nan], [math.nan], higher_is_better=False,
                        cost_label="s", acc_label="err", title="t")
    assert empty.is_file()

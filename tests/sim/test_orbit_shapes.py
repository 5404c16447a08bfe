"""Orbit trajectories: circle, helix, spiral and rounded square keep the ROV's speed and their declared shape."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.errors import ConfigError
from cadalign.sim.spec import TrajectorySpec
from cadalign.sim.trajectory import frame_poses, pose_at


def _eyes(spec: TrajectorySpec, n: int) -> np.ndarray:
    return np.array([p.t for p in frame_poses(spec, n)])


def test_plain_circle_is_unchanged() -> None:
    """No helix/spiral/square knobs: the camera is on the circle at azimuth s / r, as before the knobs existed."""
    spec = TrajectorySpec(radius_m=9.0, height_m=3.0, speed_mps=0.5, fps=0.5, jitter_m=0.0, start_deg=30.0)
    eyes = _eyes(spec, 20)
    az = np.radians(30.0) + 0.5 * np.arange(20) / 0.5 / 9.0
    np.testing.assert_allclose(eyes[:, :2], 9.0 * np.stack([np.cos(az), np.sin(az)], 1), atol=1e-9)
    np.testing.assert_allclose(eyes[:, 2], 3.0)


def test_helix_descends_per_lap_and_sees_each_azimuth_twice() -> None:
    spec = TrajectorySpec(radius_m=10.0, height_m=5.0, climb_m_per_lap=-1.5, speed_mps=1.0, fps=1.0, jitter_m=0.0)
    lap_s = 2 * np.pi * 10.0
    one_lap = pose_at(spec, lap_s).t
    np.testing.assert_allclose(one_lap, [10.0, 0.0, 3.5], atol=1e-6)
    np.testing.assert_allclose(pose_at(spec, 2 * lap_s).t, [10.0, 0.0, 2.0], atol=1e-6)


@pytest.mark.parametrize("squareness, step", [(2.0, -1.0), (4.0, 0.0), (6.0, -0.5)])
def test_speed_is_constant_along_spirals_and_rounded_squares(squareness: float, step: float) -> None:
    spec = TrajectorySpec(radius_m=8.0, height_m=4.0, climb_m_per_lap=-1.0, radius_step_m_per_lap=step,
                          squareness=squareness, speed_mps=0.5, fps=0.5, jitter_m=0.0)
    steps = np.linalg.norm(np.diff(_eyes(spec, 90), axis=0), axis=1)
    # speed / fps = 1 m of path between frames; a chord is never longer than its arc and, on these gentle bends,
    # less than 2 % shorter
    assert steps.max() <= 1.0 + 1e-6 and steps.min() >= 0.98


def test_rounded_square_keeps_radius_at_the_sides_and_widens_at_the_corners() -> None:
    spec = TrajectorySpec(radius_m=8.0, height_m=4.0, squareness=4.0, speed_mps=0.2, fps=1.0, jitter_m=0.0)
    eyes = _eyes(spec, 260)
    az = np.degrees(np.arctan2(eyes[:, 1], eyes[:, 0]))
    r = np.hypot(eyes[:, 0], eyes[:, 1])
    assert r.min() == pytest.approx(8.0, abs=1e-3)
    side = r[np.abs(az) < 1.0]
    corner = r[np.abs(az - 45.0) < 1.0]
    assert side.size and corner.size
    np.testing.assert_allclose(side, 8.0, atol=2e-3)
    np.testing.assert_allclose(corner, 8.0 * 2 ** 0.25, atol=2e-2)  # |x|^4 + |y|^4 = r^4 at x = y
    # the camera still looks at the centre
    fwd = np.array([p.R[:, 2] for p in frame_poses(spec, 30)])
    to_c = np.asarray(spec.center) - _eyes(spec, 30)
    np.testing.assert_allclose(fwd, to_c / np.linalg.norm(to_c, axis=1, keepdims=True), atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(r=st.floats(1.0, 30.0), step=st.floats(-3.0, 3.0), sq=st.floats(2.0, 20.0), t=st.floats(0.0, 400.0))
def test_orbit_is_finite_or_refused(r: float, step: float, sq: float, t: float) -> None:
    """Any orbit gives a finite rotation and centre, or refuses a spiral that reaches the centre, naming the knob."""
    spec = TrajectorySpec(radius_m=r, height_m=3.0, radius_step_m_per_lap=step, squareness=sq, speed_mps=0.5,
                          jitter_m=0.0)
    try:
        pose = pose_at(spec, t)
    except ConfigError as e:
        assert step < 0 and "radius_step_m_per_lap" in str(e)
        return
    assert np.isfinite(pose.t).all() and np.isfinite(pose.R).all()
    np.testing.assert_allclose(pose.R.T @ pose.R, np.eye(3), atol=1e-9)


def test_squareness_below_two_is_refused() -> None:
    from cadalign.config import from_dict

    with pytest.raises(ConfigError, match="squareness"):
        from_dict(TrajectorySpec, {"squareness": 1.0})


def test_an_inward_spiral_flies_until_it_reaches_the_centre() -> None:
    """Refused exactly when the path flown is longer than the spiral (r from 10 m to 0.5 m at -3 m per lap: about
    3.2 laps, ~110 m), not before."""
    spec = TrajectorySpec(radius_m=10.0, height_m=3.0, radius_step_m_per_lap=-3.0, speed_mps=1.0, jitter_m=0.0)
    laps = (10.0 - 0.5) / 3.0
    length = 2 * np.pi * (10.0 * laps - 3.0 * laps**2 / 2)  # integral of r(theta) dtheta
    ok = pose_at(spec, 0.97 * length)
    assert np.hypot(*ok.t[:2]) < 2.0
    with pytest.raises(ConfigError, match="reaches the centre"):
        pose_at(spec, 1.03 * length)

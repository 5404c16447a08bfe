"""ROV trajectories as functions of time: orbit (circle, helix, spiral, rounded square), lawnmower, approach, hover.

A trajectory maps time t (seconds) to ``T_world_from_cam`` (OpenCV camera:
x right, y down, z forward). The ROV moves along its path at ``speed_mps``;
frame k is taken at ``t = k / fps``. Smooth jitter (sum of sinusoids with
seeded phases) imitates station keeping.
"""

from __future__ import annotations

import functools

import numpy as np

from cadalign.errors import ConfigError
from cadalign.sim.scene_spec import TrajectorySpec
from cadalign.types import Rigid3

WORLD_UP = np.array([0.0, 0.0, 1.0])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = WORLD_UP) -> Rigid3:
    """``T_world_from_cam`` of a camera at ``eye`` looking at ``target`` with image-up along ``up``.

    Falls back to the world x axis as the up hint when the view direction is
    (anti)parallel to ``up``, so looking straight down is well defined.
    """
    f = np.asarray(target, float) - np.asarray(eye, float)
    norm = np.linalg.norm(f)
    if norm < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    f /= norm
    r = np.cross(f, up)
    if np.linalg.norm(r) < 1e-6:
        r = np.cross(f, np.array([1.0, 0.0, 0.0]))
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    return Rigid3(np.stack([r, d, f], axis=1), eye)


def _jitter(spec: TrajectorySpec, t: float, seed: int) -> np.ndarray:
    if spec.jitter_m == 0:
        return np.zeros(3)
    rng = np.random.default_rng([seed, 7])
    freqs = rng.uniform(0.05, 0.4, size=(3, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(3, 3))
    return spec.jitter_m / np.sqrt(3) * np.sin(2 * np.pi * freqs * t + phases).sum(axis=1)


def _lawnmower_polyline(spec: TrajectorySpec) -> np.ndarray:
    cx, cy, _ = spec.center
    ax, ay = spec.area_m
    n_lines = max(int(np.floor(ay / spec.line_spacing_m)) + 1, 1)
    ys = cy - ay / 2 + np.arange(n_lines) * spec.line_spacing_m
    pts = []
    for i, y in enumerate(ys):
        xs = (cx - ax / 2, cx + ax / 2) if i % 2 == 0 else (cx + ax / 2, cx - ax / 2)
        pts += [(xs[0], y), (xs[1], y)]
    return np.array(pts)


def _along_polyline(pts: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Position and unit heading at arc length ``s`` (clamped to the ends)."""
    seg = np.diff(pts, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    s = float(np.clip(s, 0.0, cum[-1]))
    i = int(np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1))
    heading = seg[i] / max(lengths[i], 1e-12)
    return pts[i] + heading * (s - cum[i]), heading


_ORBIT_SAMPLES_PER_LAP = 2048


@functools.lru_cache(maxsize=8)
def _orbit_path(spec: TrajectorySpec, laps: int) -> tuple[np.ndarray, np.ndarray, bool]:
    """(cumulative arc length (N,), eye positions (N, 3), whether the spiral ended) of ``laps`` turns of the
    orbit, densely sampled.

    The plan shape is the superellipse ``|x|^n + |y|^n = r^n`` (``n = squareness``; 2 is a circle) whose
    ``r`` changes by ``radius_step_m_per_lap`` per turn, and the height by ``climb_m_per_lap``. An inward spiral
    ends where ``r`` falls to 5 % of ``radius_m``.
    """
    theta = np.linspace(0.0, 2 * np.pi * laps, _ORBIT_SAMPLES_PER_LAP * laps + 1)
    r = spec.radius_m + spec.radius_step_m_per_lap * theta / (2 * np.pi)
    keep = r > 0.05 * spec.radius_m
    ended = not keep.all()
    theta, r = theta[keep], r[keep]
    az = np.radians(spec.start_deg) + theta
    c, s = np.cos(az), np.sin(az)
    n = spec.squareness
    r = r / (np.abs(c) ** n + np.abs(s) ** n) ** (1.0 / n)
    eye = np.stack([spec.center[0] + r * c, spec.center[1] + r * s,
                    spec.height_m + spec.climb_m_per_lap * theta / (2 * np.pi)], axis=1)
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(eye, axis=0), axis=1))])
    return cum, eye, ended


def _orbit_eye(spec: TrajectorySpec, s: float) -> np.ndarray:
    """Camera centre after arc length ``s`` along the orbit (a circle, helix, spiral or rounded square).

    Raises:
        ConfigError: an inward spiral reaches the centre before ``s``.
    """
    if spec.squareness == 2.0 and spec.radius_step_m_per_lap == 0.0:
        # the plain circle or helix in closed form (``s`` counted in plan; a helix's climb adds < 0.1 %)
        az = np.radians(spec.start_deg) + s / spec.radius_m
        laps = s / (2 * np.pi * spec.radius_m)
        return np.array([spec.center[0] + spec.radius_m * np.cos(az), spec.center[1] + spec.radius_m * np.sin(az),
                         spec.height_m + spec.climb_m_per_lap * laps])
    laps = max(int(np.ceil(s / (2 * np.pi * spec.radius_m))) + 1, 1)
    while True:
        cum, eye, ended = _orbit_path(spec, laps)
        if cum[-1] >= s:
            return np.array([np.interp(s, cum, eye[:, k]) for k in range(3)])
        if ended:
            raise ConfigError(f"trajectory: the orbit spiral (radius_m = {spec.radius_m}, radius_step_m_per_lap = "
                              f"{spec.radius_step_m_per_lap}) reaches the centre after {cum[-1]:.1f} m of the "
                              f"{s:.1f} m flown; make radius_step_m_per_lap less negative or fly fewer frames")
        laps += max(laps // 2, 1)


def pose_at(spec: TrajectorySpec, t: float, seed: int = 0) -> Rigid3:
    """``T_world_from_cam`` at time ``t`` seconds."""
    centre = np.asarray(spec.center, dtype=float)
    s = spec.speed_mps * t
    az0 = np.radians(spec.start_deg)
    if spec.kind == "orbit":
        eye = _orbit_eye(spec, s)
        target = centre
    elif spec.kind == "approach":
        dist = max(spec.radius_m - s, min(spec.standoff_m, spec.radius_m))
        eye = np.array([centre[0] + dist * np.cos(az0), centre[1] + dist * np.sin(az0), spec.height_m])
        target = centre
    elif spec.kind == "hover":
        eye = np.array(
            [centre[0] + spec.radius_m * np.cos(az0), centre[1] + spec.radius_m * np.sin(az0), spec.height_m]
        )
        target = centre
    else:  # lawnmower
        xy, heading = _along_polyline(_lawnmower_polyline(spec), s)
        eye = np.array([xy[0], xy[1], spec.height_m])
        pitch = np.radians(spec.pitch_down_deg)
        fwd = np.array([heading[0] * np.cos(pitch), heading[1] * np.cos(pitch), -np.sin(pitch)])
        target = eye + fwd
    jit = _jitter(spec, t, seed)
    return look_at(eye + jit, target + 0.5 * jit)


def frame_poses(spec: TrajectorySpec, n_frames: int, seed: int = 0) -> list[Rigid3]:
    """``T_world_from_cam`` for frames ``k = 0..n-1`` at ``t = k / fps``."""
    return [pose_at(spec, k / spec.fps, seed) for k in range(n_frames)]

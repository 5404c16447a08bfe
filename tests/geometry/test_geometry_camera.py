"""Pinhole camera: intrinsics, projection, pixel-centre convention, FOV, and focal/shift recovery."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from geometry_testdata import DETERMINISTIC, seeds
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.errors import DegenerateGeometryError, InputError
from cadalign.geometry import (
    backproject,
    decompose_intrinsics,
    depth_to_points,
    focal_to_fov,
    fov_to_focal,
    intrinsics,
    pixel_rays,
    project,
    recover_focal_shift,
)
from cadalign.types import Camera

K = intrinsics(500.0, 480.0, 320.0, 240.0)
W, H = 640, 480


@settings(max_examples=30, **DETERMINISTIC)
@given(st.floats(1, 1e4), st.floats(1, 1e4), st.floats(-1e3, 1e3), st.floats(-1e3, 1e3))
def test_intrinsics_build_decompose_round_trip(fx: float, fy: float, cx: float, cy: float) -> None:
    Kb = intrinsics(fx, fy, cx, cy)
    assert Kb.shape == (3, 3) and np.array_equal(Kb[2], [0, 0, 1]) and Kb[0, 1] == 0 and Kb[1, 0] == 0
    assert decompose_intrinsics(Kb) == (fx, fy, cx, cy)
    cam = Camera(Kb, 64, 48)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (fx, fy, cx, cy)


@pytest.mark.parametrize("args", [(0, 1, 0, 0), (1, -1, 0, 0), (np.nan, 1, 0, 0), (1, 1, np.inf, 0)])
def test_intrinsics_rejects(args: tuple[float, ...]) -> None:
    with pytest.raises(InputError):
        intrinsics(*args)


def test_decompose_rejects_skew_and_bad_matrices() -> None:
    skewed = K.copy()
    skewed[0, 1] = 1.0
    for bad in (skewed, np.eye(4), np.diag([1.0, 1.0, 2.0]), np.full((3, 3), np.nan), np.diag([-1.0, 1.0, 1.0])):
        with pytest.raises(InputError):
            decompose_intrinsics(bad)


def test_optical_axis_projects_to_principal_point() -> None:
    uv, valid = project(K, np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 1e4]]))
    assert valid.all() and np.array_equal(uv, [[320.0, 240.0], [320.0, 240.0]])


def test_pixel_centres_are_at_i_plus_half() -> None:
    """COLMAP/OpenGL convention: the ray through pixel (i, j)'s centre projects to (i + 0.5, j + 0.5)."""
    rays = pixel_rays(K, 8, 6)
    assert rays.shape == (6, 8, 3) and np.all(rays[..., 2] == 1.0)
    uv, valid = project(K, rays.reshape(-1, 3) * 3.0)
    jj, ii = np.mgrid[0:6, 0:8]
    assert valid.all()
    assert np.allclose(uv, np.c_[ii.ravel() + 0.5, jj.ravel() + 0.5], atol=1e-12)
    # with a centred principal point (cx = W / 2) the image centre lies between the two middle pixels
    Kc = intrinsics(100.0, 100.0, 4.0, 3.0)
    r = pixel_rays(Kc, 8, 6)
    assert np.allclose(r[2, 3, :2] + r[3, 4, :2], 0.0, atol=1e-15)
    unit = pixel_rays(K, 8, 6, normalize=True)
    assert np.allclose(np.linalg.norm(unit, axis=-1), 1.0, atol=1e-15)


@settings(max_examples=30, **DETERMINISTIC)
@given(seeds, st.floats(-50, 50))
def test_project_backproject_round_trip(seed: int, skew: float) -> None:
    rng = np.random.default_rng(seed)
    Ks = K.copy()
    Ks[0, 1] = skew
    X = np.c_[rng.uniform(-5, 5, (50, 2)), rng.uniform(0.1, 100, 50)]
    uv, valid = project(Ks, X)
    assert valid.all()
    Xb, valid_b = backproject(Ks, uv, X[:, 2])
    assert valid_b.all()
    assert np.allclose(Xb, X, rtol=1e-12, atol=1e-12)


def test_depth_image_back_projects_onto_pixel_centres() -> None:
    depth = np.random.default_rng(0).uniform(0.5, 20, (48, 64))
    depth[0, 0], depth[1, 1], depth[2, 2], depth[3, 3] = 0.0, -1.0, np.nan, np.inf
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        pts, valid = depth_to_points(K, depth)
    assert pts.shape == (48, 64, 3)
    assert valid.sum() == 48 * 64 - 4 and not valid[[0, 1, 2, 3], [0, 1, 2, 3]].any()
    assert np.all(np.isnan(pts[~valid]))
    uv, ok = project(K, pts[valid])
    jj, ii = np.nonzero(valid)
    assert ok.all() and np.allclose(uv, np.c_[ii + 0.5, jj + 0.5], atol=1e-9)
    assert np.allclose(pts[valid][:, 2], depth[valid], rtol=1e-15)


def test_invalid_points_are_flagged_not_projected() -> None:
    X = np.array(
        [
            [0.1, 0.2, 1.0],  # ok
            [0.1, 0.2, 0.0],  # on the camera plane
            [0.1, 0.2, -2.0],  # behind
            [0.1, 0.2, 1e-12],  # within eps of the camera plane
            [np.nan, 0.0, 1.0],
            [0.0, 0.0, np.nan],
            [np.inf, 0.0, 1.0],
            [1e300, 0.0, 1e-300 + 1e-6],  # finite but overflows
        ]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        uv, valid = project(K, X)
        Xb, valid_b = backproject(
            K, np.array([[1.0, 2.0], [1.0, np.nan], [1.0, 2.0], [1.0, 2.0]]), np.array([1.0, 1.0, 0.0, np.nan])
        )
    assert valid.tolist() == [True] + [False] * 7
    assert np.all(np.isnan(uv[~valid]))
    assert valid_b.tolist() == [True, False, False, False]
    assert np.all(np.isnan(Xb[~valid_b]))


def test_shape_errors() -> None:
    with pytest.raises(InputError):
        project(K, np.zeros((3, 2)))
    with pytest.raises(InputError):
        backproject(K, np.zeros((3, 2)), np.zeros(4))
    with pytest.raises(InputError):
        depth_to_points(K, np.zeros(5))
    with pytest.raises(InputError):
        pixel_rays(K, 0, 5)


@settings(max_examples=40, **DETERMINISTIC)
@given(st.floats(1e-3, np.pi - 1e-3), st.integers(1, 10_000))
def test_fov_focal_round_trip(fov: float, size: int) -> None:
    f = fov_to_focal(fov, size)
    assert focal_to_fov(f, size) == pytest.approx(fov, rel=1e-13)


def test_fov_known_values_and_rejects() -> None:
    assert fov_to_focal(np.pi / 2, 640) == pytest.approx(320.0, rel=1e-15)  # 90 deg: f = W / 2
    assert focal_to_fov(320.0, 640) == pytest.approx(np.pi / 2, rel=1e-15)
    for args in ((0.0, 640), (np.pi, 640), (1.0, 0), (np.nan, 640)):
        with pytest.raises(InputError):
            fov_to_focal(*args)
    for args in ((0.0, 640), (1.0, -1), (np.inf, 640)):
        with pytest.raises(InputError):
            focal_to_fov(*args)


# --- focal / z-shift recovery (GenLaM / MoGe) ------------------------------------------------------------------


def _point_map(f: float, dz: float, depth: np.ndarray) -> np.ndarray:
    """(H, W, 3) point map of true z-depth ``depth`` seen with focal ``f``, then z-shifted by ``-dz``."""
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w) + 0.5 - 0.5 * w, np.arange(h) + 0.5 - 0.5 * h)
    return np.stack([u * depth / f, v * depth / f, depth - dz], axis=-1)


def _scene_depth(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """A tilted plane plus a bump: varied but smooth depth, 1..~6 m."""
    u, v = np.meshgrid(np.linspace(-1, 1, w), np.linspace(-1, 1, h))
    g = rng.uniform(-0.5, 0.5, 2)
    return 3.0 + g[0] * u + g[1] * v + rng.uniform(0.2, 2) * np.exp(-4 * (u**2 + v**2))


@settings(max_examples=25, **DETERMINISTIC)
@given(seeds, st.floats(50, 5000), st.floats(-0.9, 20), st.sampled_from([1e-3, 1.0, 1e3]))
def test_recover_focal_shift_exact(seed: int, f: float, dz: float, unit: float) -> None:
    """Noiseless point maps in any unit (mm, m, km): f and the shift come back to ~1e-9 relative."""
    depth = _scene_depth(24, 32, np.random.default_rng(seed))
    f_est, dz_est = recover_focal_shift(unit * _point_map(f, dz, depth))
    assert f_est == pytest.approx(f, rel=1e-9)
    assert dz_est / unit == pytest.approx(dz, rel=1e-9, abs=1e-9)


def test_recover_focal_shift_with_masked_pixels_and_explicit_uv() -> None:
    depth = _scene_depth(30, 40, np.random.default_rng(1))
    P = _point_map(400.0, 0.5, depth)
    P[::3, ::2] = np.nan  # masked pixels are dropped, not fatal
    assert recover_focal_shift(P) == pytest.approx((400.0, 0.5), rel=1e-9)
    u, v = np.meshgrid(np.arange(40) + 0.5 - 20, np.arange(30) + 0.5 - 15)
    uv = np.stack([u, v], -1).reshape(-1, 2)
    assert recover_focal_shift(P.reshape(-1, 3), uv) == pytest.approx((400.0, 0.5), rel=1e-9)


def test_recover_focal_shift_with_noise() -> None:
    rng = np.random.default_rng(2)
    depth = _scene_depth(48, 64, rng)
    P = _point_map(600.0, 1.0, depth) * (1 + 1e-3 * rng.standard_normal((48, 64, 1)))
    f_est, dz_est = recover_focal_shift(P)
    assert f_est == pytest.approx(600.0, rel=0.02) and dz_est == pytest.approx(1.0, abs=0.05)


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda P: P[:2, :3], "needs >= 8 finite points"),
        (lambda P: np.full_like(P, np.nan), "needs >= 8 finite points"),
        (lambda P: np.where(np.arange(P[..., 0].size).reshape(P.shape[:2])[..., None] < 7, P, np.nan), "got 7"),
        (lambda P: _point_map(400.0, 0.0, np.full(P.shape[:2], 2.0)), "same depth"),  # fronto-parallel
        (
            lambda P: _point_map(400.0, 0.0, 2.0 + 1e-7 * np.random.default_rng(0).standard_normal(P.shape[:2])),
            "depth varies too little",
        ),  # fronto-parallel up to noise: f and shift still inseparable
        (lambda P: np.concatenate([np.zeros_like(P[..., :2]), P[..., 2:]], -1), "optical axis"),
        (lambda P: P * np.array([-1.0, -1.0, 1.0]), "f <= 0"),  # mirrored: no pinhole fits
    ],
)
def test_recover_focal_shift_rejects_degenerate(make: object, match: str) -> None:
    P = _point_map(400.0, 0.5, _scene_depth(12, 16, np.random.default_rng(3)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(DegenerateGeometryError, match=match):
            recover_focal_shift(make(P))  # type: ignore[operator]


def test_recover_focal_shift_shape_errors() -> None:
    with pytest.raises(InputError):
        recover_focal_shift(np.zeros((10, 3)))  # (N, 3) needs uv
    with pytest.raises(InputError):
        recover_focal_shift(np.zeros((10, 3)), np.zeros((9, 2)))
    with pytest.raises(InputError):
        recover_focal_shift(np.zeros((4, 5, 4)))


@settings(max_examples=30, **DETERMINISTIC)
@given(seeds, st.integers(8, 40))
def test_recover_focal_shift_on_arbitrary_data_is_valid_or_raises(seed: int, n: int) -> None:
    """Inconsistent inputs give a valid pinhole (f > 0, all Z + dz > 0) or the project's error; never a warning."""
    rng = np.random.default_rng(seed)
    P = rng.standard_normal((n, 3)) * rng.uniform(0.1, 10, 3) + rng.uniform(-5, 5, 3)
    uv = 100 * rng.standard_normal((n, 2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            f, dz = recover_focal_shift(P, uv)
        except DegenerateGeometryError:
            return
    assert np.isfinite(f) and f > 0 and np.isfinite(dz) and np.all(P[:, 2] + dz > 0)

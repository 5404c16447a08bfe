"""Numerical stability: extreme-but-valid inputs give finite results or the project's error, never a RuntimeWarning.

Every test here runs with RuntimeWarning turned into an error (``-W error::RuntimeWarning`` semantics).
It adds what ``tests/geometry`` does not already cover: hypothesis sweeps of projection / back-projection
over 600 orders of magnitude and float32 input, BOP depth encoding of 0/NaN/inf/huge depth and extreme
depth scales, Sim(3) scale near 0 and huge (types and ``sim3_from_matrix``), Umeyama on the minimum
three points 1e6 m away and float32-vs-float64 agreement, plane fits on nearly collinear points, CAD
cleaning at absurd scales, frame checks on constant images and scene trajectories with absurd sizes.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from cadalign.cad.clean import clean_mesh
from cadalign.config import from_dict
from cadalign.errors import CadalignError, ConfigError, DegenerateGeometryError
from cadalign.formats.bop import decode_depth, encode_depth
from cadalign.geometry import backproject, depth_to_points, fit_plane, geodesic_angle, project, umeyama
from cadalign.geometry.transforms import sim3_from_matrix
from cadalign.sfm.config import FrameConfig
from cadalign.sfm.frames import enhance, exposure_problem, motion_between, select_frames, sharpness
from cadalign.sim.spec import SceneSpec, check_camera_clearance
from cadalign.types import Rigid3, Sim3

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")
FAST = settings(max_examples=60, deadline=None, derandomize=True, database=None)
K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])
EPS32 = float(np.finfo(np.float32).eps)

#: Any finite float64, with extra weight on zero, subnormals, the edges of the range and near-zero values.
extreme = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from([0.0, -0.0, 5e-324, -5e-324, 1e-300, 1e-9, 1e300, -1e300, 1.7976931348623157e308]),
)
log_scale = st.floats(-320.0, 308.0).map(lambda e: 10.0**e)


# ---------------------------------------------------------------------------------------- projection, depth


@FAST
@given(pts=st.lists(st.tuples(extreme, extreme, extreme), min_size=1, max_size=12), f32=st.booleans())
def test_project_any_finite_points(pts: list[tuple[float, float, float]], f32: bool) -> None:
    X = np.array(pts)
    if f32:
        with np.errstate(over="ignore"):  # beyond float32 range -> inf: a legitimate bad input
            X = X.astype(np.float32)
    uv, valid = project(K, X)
    assert np.all(np.isfinite(uv[valid])) and np.all(np.isnan(uv[~valid]))
    assert np.all(X[valid, 2] > 1e-9)


@pytest.mark.parametrize("z", [1e-9 * (1 + 1e-15), 2e-9, 1e-6, 1e-3])
def test_project_as_z_goes_to_zero_stays_finite_or_invalid(z: float) -> None:
    X = np.array([[0.5, -0.25, z], [0.0, 0.0, z], [1e6, 1e6, z]])
    uv, valid = project(K, X)
    assert valid[1] and np.array_equal(uv[1], K[:2, 2])
    assert np.all(np.isfinite(uv[valid])) and np.all(np.isnan(uv[~valid]))


@FAST
@given(depth=st.lists(extreme | st.sampled_from([math.nan, math.inf, -math.inf]), min_size=6, max_size=6),
       f32=st.booleans())
def test_backproject_and_depth_image_any_depth(depth: list[float], f32: bool) -> None:
    d = np.array(depth)
    if f32:
        with np.errstate(over="ignore"):
            d = d.astype(np.float32)
    uv = np.array([[0.5, 0.5], [639.5, 479.5], [320.0, 240.0], [1e9, -1e9], [0.0, 0.0], [100.0, 50.0]])
    pts, valid = backproject(K, uv, d)
    assert np.all(np.isfinite(pts[valid])) and np.all(np.isnan(pts[~valid]))
    assert not np.any(valid & ~(d > 0))
    img, valid_img = depth_to_points(K, d.reshape(2, 3))
    assert np.all(np.isfinite(img[valid_img])) and valid_img.sum() <= valid.sum() + 6


def test_project_backproject_float32_agrees_with_float64() -> None:
    rng = np.random.default_rng(0)
    X = rng.uniform([-3, -2, 0.5], [3, 2, 40.0], (500, 3))
    uv64, _ = project(K, X)
    uv32, _ = project(K.astype(np.float32), X.astype(np.float32))
    assert np.abs(uv32 - uv64).max() < 4 * EPS32 * np.abs(uv64).max()  # only the input rounding differs
    P64, _ = backproject(K, uv64, X[:, 2])
    P32, _ = backproject(K, uv64.astype(np.float32), X[:, 2].astype(np.float32))
    assert np.abs(P32 - P64).max() < 8 * EPS32 * np.abs(P64).max()


@FAST
@given(depth=st.lists(extreme | st.sampled_from([math.nan, math.inf, -math.inf]), min_size=4, max_size=4),
       scale=log_scale)
def test_bop_depth_encoding_any_depth_and_scale(depth: list[float], scale: float) -> None:
    d = np.array(depth)
    if not 0 < scale <= 1e30:
        with pytest.raises(CadalignError, match="depth_scale"):
            encode_depth(d, scale)
        return
    png = encode_depth(d, scale)
    assert png.dtype == np.uint16 and np.all(png[~(d > 0) | ~np.isfinite(d)] == 0)
    back = decode_depth(png, scale)
    assert back.dtype == np.float32 and np.all(np.isfinite(back))
    kept = png > 0
    np.testing.assert_allclose(back[kept], d[kept], rtol=1e-6, atol=0.5 * scale / 1000 * (1 + 1e-6))


def test_bop_depth_float32_and_float64_encode_alike() -> None:
    d = np.random.default_rng(1).uniform(0.2, 30.0, (48, 64))
    for scale in (0.1, 1.0, 10.0):
        diff = encode_depth(d.astype(np.float32), scale).astype(int) - encode_depth(d, scale).astype(int)
        assert np.abs(diff).max() <= 1  # float32 depth rounds to the neighbouring unit at most
    with pytest.raises(CadalignError, match="depth_scale"):
        encode_depth(d, 0.0)  # would silently write "no depth" everywhere


# ------------------------------------------------------------------------------------------------- Sim(3)


@FAST
@given(s=log_scale, t=st.tuples(extreme, extreme, extreme), x=st.tuples(extreme, extreme, extreme))
def test_sim3_any_scale_is_finite_or_an_error(s: float, t: tuple, x: tuple) -> None:
    R = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix()
    try:
        S = Sim3(s, R, t)
    except DegenerateGeometryError:
        assert s == 0.0 or not math.isfinite(s)
        return
    for op in (S.inverse, lambda: S @ S, lambda: S.apply(np.array(x)), lambda: S.inverse() @ S):
        try:
            out = op()
        except CadalignError:
            continue
        values = out if isinstance(out, np.ndarray) else np.r_[out.s, out.t, out.R.ravel()]
        assert np.all(np.isfinite(values))


@pytest.mark.parametrize("s", [1e-150, 1e-30, 1e-6, 1.0, 1e6, 1e30, 1e150])
def test_sim3_round_trip_at_extreme_scales(s: float) -> None:
    S = Sim3(s, Rotation.from_rotvec([0.1, 0.7, -0.4]).as_matrix(), np.array([1e3, -2.0, 5.0]) * s)
    x = np.array([[0.3, -1.2, 2.0], [10.0, 0.0, -4.0]])
    np.testing.assert_allclose(S.inverse().apply(S.apply(x)), x, rtol=1e-9, atol=1e-9)
    ident = S.inverse() @ S
    assert ident.s == pytest.approx(1.0, rel=1e-12) and np.allclose(ident.t, 0, atol=1e-9 * max(1.0, 1e3))


@pytest.mark.parametrize("s", [1e-100, 1e-10, 1.0, 1e10, 1e100])
def test_sim3_from_matrix_recovers_extreme_scales(s: float) -> None:
    S = Sim3(s, Rotation.from_rotvec([0.2, 0.1, 0.3]).as_matrix(), [1.0, 2.0, 3.0])
    back = sim3_from_matrix(S.matrix())
    assert back.s == pytest.approx(s, rel=1e-12) and geodesic_angle(back.R, S.R) < 1e-12


def test_rigid3_apply_overflow_is_an_error_not_inf() -> None:
    T = Rigid3(np.eye(3), [1e308, 0.0, 0.0])
    with pytest.raises(DegenerateGeometryError, match="overflowed"):
        T.apply(np.array([[1e308, 0.0, 0.0]]))
    nan_rows = T.apply(np.array([[np.nan, 0.0, 0.0]]))  # NaN in -> NaN out (masked points), no error
    assert np.isnan(nan_rows[0, 0])


# ----------------------------------------------------------------------------------- Umeyama and plane fits


def _rot(seed: int) -> np.ndarray:
    return Rotation.random(random_state=seed).as_matrix()


@pytest.mark.parametrize("offset", [1e6, 5e6])
def test_umeyama_three_points_far_from_origin(offset: float) -> None:
    src = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 1.5, 0.3]]) + offset
    R, s, t = _rot(3), 0.01, np.array([-offset, 2 * offset, 10.0])
    dst = s * src @ R.T + t
    est = umeyama(src, dst)
    # the data itself is exact only to eps * |dst| (~2e6 m) over a 0.02 m spread: ~2e-8 relative
    assert est.s == pytest.approx(s, rel=2e-6) and geodesic_angle(est.R, R) < 2e-6
    np.testing.assert_allclose(est.apply(src), dst, atol=1e-6 * offset * s + 1e-6)


@FAST
@given(spread=st.sampled_from([0.0, 1e-15, 1e-12, 1e-9, 1e-6, 1e-3]), offset=st.sampled_from([0.0, 1e3, 1e6]),
       n=st.integers(3, 8), seed=st.integers(0, 2**16))
def test_umeyama_nearly_collinear_is_accurate_or_refused(spread: float, offset: float, n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    line = np.outer(np.linspace(-1, 1, n), [1.0, 2.0, -0.5]) + rng.normal(0, 1, (n, 3)) * spread + offset
    R, t = _rot(seed), rng.normal(0, 10, 3)
    try:
        est = umeyama(line, line @ R.T + t)
    except DegenerateGeometryError:
        return
    assert np.isfinite(est.s) and np.all(np.isfinite(est.t))
    np.testing.assert_allclose(est.apply(line), line @ R.T + t, atol=1e-6 * (1 + offset))


@pytest.mark.parametrize("offset", [0.0, 100.0, 1e4])
def test_umeyama_float32_inputs_agree_with_float64_within_input_rounding(offset: float) -> None:
    rng = np.random.default_rng(5)
    src = rng.uniform(-2, 2, (40, 3)) + offset
    R, s, t = _rot(5), 1.7, np.array([3.0, -1.0, 0.5])
    dst = s * src @ R.T + t
    e64 = umeyama(src, dst)
    e32 = umeyama(src.astype(np.float32), dst.astype(np.float32))
    rel = EPS32 * (1 + offset / 2.0)  # float32 rounding of the coordinates, relative to the 2 m spread
    assert abs(e32.s - e64.s) < 20 * rel * s and geodesic_angle(e32.R, e64.R) < 20 * rel


@FAST
@given(spread=st.sampled_from([0.0, 1e-14, 1e-10, 1e-7, 1e-4]), offset=st.sampled_from([0.0, 1e2, 1e6]),
       seed=st.integers(0, 2**16))
def test_plane_fit_nearly_collinear_is_a_plane_or_refused(spread: float, offset: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    pts = np.outer(rng.uniform(-1, 1, 12), [0.3, 1.0, 0.2]) + offset
    pts[:, 2] += rng.normal(0, 1, 12) * spread
    try:
        plane = fit_plane(pts)
    except DegenerateGeometryError:
        return
    assert np.linalg.norm(plane.normal) == pytest.approx(1.0, abs=1e-12)
    assert np.all(np.isfinite(plane.signed_distance(pts)))


# ------------------------------------------------------------------------------------------- CAD, frames, sim


@pytest.mark.parametrize("exponent", [-320, -200, -12, 0, 12, 99, 101, 200, 300])
def test_clean_mesh_at_absurd_scales_is_finite_or_refused(exponent: int) -> None:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]) * 10.0**exponent
    f = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])
    try:
        v2, f2, report = clean_mesh(v, f)
    except CadalignError as exc:
        assert exponent > 15 and "beyond any real object" in str(exc)
        return
    assert np.all(np.isfinite(v2)) and (len(f2) == 4) == (exponent > -6)  # collapses below the merge tolerance


@pytest.mark.parametrize("value", [0, 1, 128, 254, 255])
def test_frame_checks_on_constant_images(value: int) -> None:
    gray = np.full((48, 64), value, np.uint8)
    assert sharpness(gray) == 0.0 and motion_between(gray, gray) == 0.0
    assert exposure_problem(gray) == ("black" if value <= 12 else "overexposed" if value >= 243 else "")
    rgb = np.full((48, 64, 3), value, np.uint8)
    for mode in ("clahe", "clahe_wb"):
        assert enhance(rgb, FrameConfig(enhance=mode)).dtype == np.uint8
    decisions = [d for d, _ in select_frames([(f"{k}.png", "", rgb) for k in range(3)], FrameConfig())]
    assert all(np.isfinite([d.sharpness, d.motion]).all() for d in decisions)


@FAST
@given(radius=log_scale, height=st.floats(-1e300, 1e300), fps=log_scale, speed=log_scale)
def test_scene_trajectory_with_absurd_sizes(radius: float, height: float, fps: float, speed: float) -> None:
    data = {"name": "x", "objects": [{"name": "b", "source": "procedural:box"}], "seabed": None,
            "trajectory": {"radius_m": radius, "height_m": height, "fps": fps, "speed_mps": speed, "frames": 5}}
    try:
        spec = from_dict(SceneSpec, data, source="scene.toml")
        check_camera_clearance(spec, "scene.toml")
    except ConfigError as exc:
        assert "scene.toml" in str(exc)

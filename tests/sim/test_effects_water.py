"""Physics tests of the water effects: attenuation, backscatter, forward scatter, and every effect's
robustness to open-water, NaN, zero and negative ranges.

Parameters come from a scene spec through :func:`cadalign.sim.effects_chain.build_chain`, the same plumbing
the simulator uses, so the tests see the water/lamps/shutter the renderer would inject.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from effects_testdata import chain_params, make_camera, make_scene
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from cadalign.sim.effects import (
    EFFECTS,
    JERLOV_TYPES,
    FrameBuffers,
    WaterParams,
    apply_effects,
    attenuation,
    backscatter,
    buffers_from_range,
    forward_scatter,
    water_from_jerlov,
)
from cadalign.sim.effects.backscatter import veiling_light
from cadalign.sim.effects.forward_scatter import LEVELS_PX, gaussian_blur, range_sigma_px
from cadalign.sim.effects_chain import build_chain
from cadalign.types import Rigid3

OCEANIC = ("I", "IA", "IB", "II", "III")
SPECIAL_RANGES = (0.0, -0.0, -1.0, np.nan, np.inf, -np.inf, 1e4, 1e30, 3e38)








def row_buffers(rgb_value: float, ranges: np.ndarray) -> FrameBuffers:
    """A 1-pixel-high frame whose pixels see a grey target at the given ranges."""
    ranges = np.asarray(ranges, dtype=np.float32)[None, :]
    cam = make_camera(ranges.shape[1], 1)
    return buffers_from_range(np.full((*ranges.shape, 3), rgb_value, np.float32), ranges, cam)


# ---------------------------------------------------------------------------------------------- attenuation


def test_attenuation_red_falls_faster_than_blue_in_jerlov_I() -> None:
    ranges = np.linspace(0.0, 40.0, 81)
    buffers = row_buffers(0.5, ranges)
    out, _ = apply_effects(buffers, build_chain(make_scene(("attenuation",), "I")), np.random.default_rng(0))
    r, g, b = out[0, :, 0], out[0, :, 1], out[0, :, 2]
    ratio = r / b
    assert ratio[0] == 1.0
    assert np.all(np.diff(ratio) < 0), "R/B must fall monotonically with range in open-ocean water"
    assert np.all(np.diff(r) < 0) and np.all(np.diff(b) < 0)
    assert np.all(r <= g) and np.all(g <= b)  # Jerlov I: red > green > blue attenuation
    beta = water_from_jerlov("I").beta_D
    np.testing.assert_allclose(out[0], 0.5 * np.exp(-np.outer(ranges, beta)), rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("jerlov", OCEANIC)
def test_oceanic_water_attenuates_red_most(jerlov: str) -> None:
    w = water_from_jerlov(jerlov)
    assert w.beta_D[0] > max(w.beta_D[1], w.beta_D[2]) > 0  # type III: blue and green are close
    assert np.all(w.beta_B >= w.beta_D)  # beta_B ~ c = K_d + b >= K_d


@pytest.mark.parametrize("jerlov", JERLOV_TYPES)
def test_water_presets_are_sane(jerlov: str) -> None:
    w = water_from_jerlov(jerlov)
    for arr in (w.beta_D, w.beta_B, w.B_inf):
        assert arr.shape == (3,) and np.all(np.isfinite(arr)) and np.all(arr >= 0)
    assert np.all(w.B_inf <= 0.3 + 1e-6)


def test_zero_attenuation_leaves_the_image_unchanged() -> None:
    buffers = row_buffers(0.7, np.array([0.0, 1.0, 100.0, np.inf, np.nan]))
    params = dataclasses.replace(chain_params("attenuation"), water=WaterParams.clear())
    np.testing.assert_array_equal(attenuation(buffers, params), buffers.rgb)


# ---------------------------------------------------------------------------------------------- backscatter


@pytest.mark.parametrize("jerlov", JERLOV_TYPES)
def test_backscatter_tends_to_veiling_light_and_vanishes_at_zero_range(jerlov: str) -> None:
    ranges = np.array([0.0, 1e4, np.inf, np.nan, 1e30])
    buffers = row_buffers(0.6, ranges)
    chain = build_chain(make_scene(("attenuation", "backscatter"), jerlov))
    out, _ = apply_effects(buffers, chain, np.random.default_rng(0))
    B_inf = water_from_jerlov(jerlov).B_inf
    np.testing.assert_array_equal(out[0, 0], buffers.rgb[0, 0])  # range 0: no water in the way
    np.testing.assert_allclose(out[0, 1], B_inf, atol=1e-6)  # 10 km: only veiling light
    for k in (2, 3, 4):  # open water (inf, NaN) and an absurd range: exactly the veiling light, never NaN
        np.testing.assert_array_equal(out[0, k], B_inf)


@settings(max_examples=30, deadline=None)
@given(jerlov=st.sampled_from(JERLOV_TYPES), z=st.floats(0.0, 200.0), dz=st.floats(1e-3, 50.0))
def test_veiling_light_grows_monotonically_to_B_inf(jerlov: str, z: float, dz: float) -> None:
    water = water_from_jerlov(jerlov)
    v = veiling_light(np.array([[z, z + dz]], np.float32), water)[0]
    assert np.all(v[0] <= v[1] + 1e-7)
    assert np.all(v >= 0) and np.all(v <= water.B_inf + 1e-7)


def test_backscatter_alone_sets_open_water_to_B_inf_whatever_the_input() -> None:
    buffers = row_buffers(0.9, np.array([np.inf, np.nan, -np.inf]))
    params = chain_params("backscatter", "3C")
    np.testing.assert_array_equal(backscatter(buffers, params)[0], np.tile(params.water.B_inf, (3, 1)))


# -------------------------------------------------------------------------- identity at range 0 (all water)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(jerlov=st.sampled_from(JERLOV_TYPES), seed=st.integers(0, 2**32 - 1), zero=st.sampled_from([0.0, -0.0, -2.0]))
def test_water_effects_are_the_identity_at_range_zero(jerlov: str, seed: int, zero: float) -> None:
    cam = make_camera(24, 16)
    rgb = np.random.default_rng(seed).uniform(0.0, 1.0, (16, 24, 3)).astype(np.float32)
    buffers = buffers_from_range(rgb, np.full((16, 24), zero, np.float32), cam)
    chain = dict(build_chain(make_scene(("attenuation", "forward_scatter", "backscatter"), jerlov)))
    for name, fn in (("attenuation", attenuation), ("forward_scatter", forward_scatter), ("backscatter", backscatter)):
        np.testing.assert_array_equal(fn(buffers, chain[name]), rgb, err_msg=name)
    out, _ = apply_effects(buffers, list(chain.items()), np.random.default_rng(0))
    np.testing.assert_array_equal(out, rgb)


# ------------------------------------------------------------------------------------------ forward scatter


def edge_buffers(range_m: float, width: int = 321, height: int = 41) -> FrameBuffers:
    """A vertical black/white edge in the middle of the image, every pixel at ``range_m``."""
    rgb = np.zeros((height, width, 3), np.float32)
    rgb[:, width // 2:] = 1.0
    return buffers_from_range(rgb, np.full((height, width), range_m, np.float32), make_camera(width, height))


def edge_profile_sigma(img: np.ndarray) -> float:
    """Standard deviation (pixels) of the line-spread function read from a blurred vertical edge."""
    row = img[img.shape[0] // 2, :, 0].astype(np.float64)
    g = np.diff(row)
    x = np.arange(g.size)
    mean = (g * x).sum() / g.sum()
    return float(np.sqrt((g * (x - mean) ** 2).sum() / g.sum()))


def test_forward_scatter_blur_grows_with_range() -> None:
    params = chain_params("forward_scatter")
    ranges = (0.0, 1.0, 2.0, 3.5, 5.0, 8.0, 12.0, 20.0, 40.0, np.inf)
    sigmas = [edge_profile_sigma(forward_scatter(edge_buffers(r), params)) for r in ranges]
    max_grad = [float(np.abs(np.diff(forward_scatter(edge_buffers(r), params)[20, :, 0])).max()) for r in ranges]
    assert sigmas[0] == 0.0 and max_grad[0] == 1.0
    assert np.all(np.diff(sigmas) >= -1e-6) and np.all(np.diff(max_grad) <= 1e-6)
    i2, i20 = ranges.index(2.0), ranges.index(20.0)
    assert max_grad[i2] > 1.5 * max_grad[i20], "an edge at 2 m must stay sharper than at 20 m"


@pytest.mark.parametrize("sigma_px", [0.5, 1.0, 1.5, 3.0, 6.0, 8.0])
def test_forward_scatter_blur_width_matches_the_model(sigma_px: float) -> None:
    params = chain_params("forward_scatter", effect_params={"forward_scatter": {"sigma_mrad_per_m": 5.0}})
    cam = make_camera(257, 65)
    range_m = sigma_px / (cam.fx * params.sigma_mrad_per_m * 1e-3)
    buffers = edge_buffers(range_m, 257, 65)
    np.testing.assert_allclose(range_sigma_px(buffers, params), sigma_px, rtol=1e-5)
    # The ladder blends two levels so that the PSF variance is the model's (the shape is not quite Gaussian).
    assert edge_profile_sigma(forward_scatter(buffers, params)) == pytest.approx(sigma_px, rel=0.04)


@pytest.mark.parametrize("sigma_px", LEVELS_PX[1:])
def test_gaussian_blur_ladder_levels_have_the_requested_width(sigma_px: float) -> None:
    img = edge_buffers(1.0, 256, 64).rgb
    assert edge_profile_sigma(gaussian_blur(img, sigma_px)) == pytest.approx(sigma_px, rel=0.05)


def test_forward_scatter_keeps_a_uniform_image_uniform() -> None:
    rng = np.random.default_rng(3)
    ranges = rng.uniform(0.0, 60.0, (48, 64)).astype(np.float32)
    ranges[:8] = np.inf
    buffers = buffers_from_range(np.full((48, 64, 3), 0.4, np.float32), ranges, make_camera(64, 48, 100.0))
    out = forward_scatter(buffers, chain_params("forward_scatter"))
    np.testing.assert_allclose(out, 0.4, rtol=1e-5)  # the per-pixel blend weights sum to one


# ------------------------------------------------------------- every effect: finite, non-negative energy


def range_maps(shape: tuple[int, int]) -> st.SearchStrategy[np.ndarray]:
    values = st.one_of(st.sampled_from(SPECIAL_RANGES), st.floats(0.0, 80.0, width=32))
    return hnp.arrays(np.float32, shape, elements=values)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(jerlov=st.sampled_from(JERLOV_TYPES), ranges=range_maps((12, 16)), seed=st.integers(0, 2**32 - 1),
       zero_normals=st.booleans(), nan_depth=st.booleans())
def test_every_effect_gives_finite_nonnegative_energy(jerlov: str, ranges: np.ndarray, seed: int,
                                                      zero_normals: bool, nan_depth: bool) -> None:
    rng = np.random.default_rng(seed)
    cam = make_camera(16, 12)
    moved = Rigid3(np.eye(3), rng.normal(0.0, 0.05, 3))
    buffers = buffers_from_range(rng.uniform(0.0, 1.0, (12, 16, 3)), ranges, cam, T_world_from_cam_prev=moved,
                                 T_world_from_cam_next=Rigid3(np.eye(3), -moved.t), frame_dt_s=0.05)
    if zero_normals:
        buffers = dataclasses.replace(buffers, normals_cam=np.zeros_like(buffers.normals_cam))
    if nan_depth:  # a renderer may write NaN or inf depth for background pixels
        depth = np.where(np.isfinite(ranges), buffers.depth_m, np.nan).astype(np.float32)
        buffers = dataclasses.replace(buffers, depth_m=depth)
    chain = build_chain(make_scene(tuple(EFFECTS), jerlov))
    for name, params in chain:
        spec = EFFECTS[name]
        out = spec.fn(buffers, params, np.random.default_rng(seed)) if spec.uses_rng else spec.fn(buffers, params)
        assert out.shape == buffers.rgb.shape and out.dtype == np.float32, name
        assert np.all(np.isfinite(out)), f"{name} produced NaN/inf"
        assert np.all(out >= 0), f"{name} produced negative energy"
    out, timings = apply_effects(buffers, chain, np.random.default_rng(seed))
    assert set(timings) == set(EFFECTS)
    assert np.all(np.isfinite(out)) and out.min() >= 0 and out.max() <= 1
    water = dict(chain)["backscatter"].water
    sky = ~np.isfinite(ranges)
    wet, _ = apply_effects(buffers, [(n, p) for n, p in chain if n in ("attenuation", "backscatter")], rng)
    np.testing.assert_array_equal(wet[sky], np.broadcast_to(water.B_inf, (int(sky.sum()), 3)))


def test_every_effect_accepts_float64_ranges_beyond_float32() -> None:
    ranges = np.array([[1e300, -1e300, np.nan, np.inf], [0.0, 5.0, 1e39, -np.inf]])
    cam = make_camera(4, 2)
    buffers = buffers_from_range(np.full((2, 4, 3), 0.5), np.zeros((2, 4)), cam, frame_dt_s=0.1,
                                 T_world_from_cam_prev=Rigid3(t=[0.01, 0.0, 0.0]))
    buffers = dataclasses.replace(buffers, range_m=ranges)  # a float64 range map, as a renderer may hand over
    for name, params in build_chain(make_scene(tuple(EFFECTS), "II")):
        spec = EFFECTS[name]
        out = spec.fn(buffers, params, np.random.default_rng(0)) if spec.uses_rng else spec.fn(buffers, params)
        assert np.all(np.isfinite(out)) and np.all(out >= 0), name

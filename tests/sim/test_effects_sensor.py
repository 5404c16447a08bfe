"""Physics tests of the lamp, marine snow, motion blur, vignetting and low-light (sensor) effects.

Parameters come from a scene spec through :func:`cadalign.sim.effects_chain.build_chain` where the scene
decides them (lamps, water, ambient level, shutter), so the tests exercise the simulator's own plumbing.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from effects_testdata import chain_params, make_camera, make_scene
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from cadalign.errors import ConfigError
from cadalign.sim.effects import (
    FrameBuffers,
    Lamp,
    LowLightParams,
    MarineSnowParams,
    MotionBlurParams,
    VignettingParams,
    WaterParams,
    apply_effects,
    artificial_light,
    buffers_from_range,
    depth_flow,
    lamp_irradiance_at,
    low_light,
    marine_snow,
    motion_blur,
    noise_std,
    sample_particles,
    vignetting,
    vignetting_gain,
    water_from_jerlov,
)
from cadalign.sim.effects_chain import build_chain
from cadalign.sim.spec import LightSpec, TrajectorySpec
from cadalign.types import Rigid3

HEADLAMP = LightSpec(offset_m=(0.0, 0.0, 0.0), direction=(0.0, 0.0, 1.0), intensity=40.0, cone_deg=30.0)








def flat_frame(width: int, height: int, range_m: float, value: float = 0.2, hfov_deg: float = 70.0,
               **poses: object) -> FrameBuffers:
    """Every pixel sees a grey surface facing the camera at the same range."""
    rgb = np.full((height, width, 3), value, np.float32)
    ranges = np.full((height, width), range_m, np.float32)
    return buffers_from_range(rgb, ranges, make_camera(width, height, hfov_deg), **poses)


def textured(width: int, height: int, seed: int = 0) -> np.ndarray:
    """(H, W, 3) float32 random texture with sharp detail, in [0.1, 0.9]."""
    return np.random.default_rng(seed).uniform(0.1, 0.9, (height, width, 3)).astype(np.float32)


def gradient_energy(img: np.ndarray, axis: int | None = None) -> float:
    gx = np.diff(img, axis=1) ** 2
    gy = np.diff(img, axis=0) ** 2
    return float(gx.sum()) if axis == 1 else float(gy.sum()) if axis == 0 else float(gx.sum() + gy.sum())


# --------------------------------------------------------------------------------------------------- lamps


@pytest.mark.parametrize("jerlov", [None, "I", "II", "9C"])
def test_lamp_irradiance_on_axis_falls_as_inverse_square_times_attenuation(jerlov: str | None) -> None:
    water = WaterParams.clear() if jerlov is None else water_from_jerlov(jerlov)
    lamp = Lamp(offset_m=(0.0, 0.0, 0.0), direction=(0.0, 0.0, 1.0), intensity=40.0, cone_deg=30.0)
    r = np.array([0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0])
    E = lamp_irradiance_at(np.stack([0 * r, 0 * r, r], axis=1), (lamp,), water.beta_D)
    np.testing.assert_allclose(E * (r**2)[:, None] / 40.0, np.exp(-np.outer(r, water.beta_D)), rtol=1e-5)


@pytest.mark.parametrize("jerlov", ["I", "II", "5C"])
@pytest.mark.parametrize("range_m", [0.5, 1.0, 2.0, 4.0, 8.0])
def test_lamp_light_seen_on_axis_is_inverse_square_times_two_way_attenuation(jerlov: str, range_m: float) -> None:
    buffers = flat_frame(33, 25, range_m)
    params = chain_params("artificial_light", jerlov, lights=(HEADLAMP,),
                          effect_params={"artificial_light": {"camera_path": True}})
    out = artificial_light(buffers, params)
    beta = water_from_jerlov(jerlov).beta_D
    rho = 0.2 / params.ambient
    expected = rho / np.pi * 40.0 / range_m**2 * np.exp(-2.0 * beta * range_m)
    np.testing.assert_allclose(out[12, 16] - 0.2, expected, rtol=1e-4)


def test_lamp_then_attenuation_chain_equals_two_way_path() -> None:
    """Lamp light on its own (``camera_path``) and lamp + ``attenuation`` in a chain agree."""
    buffers = flat_frame(33, 25, 3.0)
    scene = make_scene(("artificial_light", "attenuation"), "IB", lights=(HEADLAMP,))
    chain = build_chain(scene)
    lamp_params = dataclasses.replace(dict(chain)["artificial_light"], camera_path=True)
    beta = dict(chain)["attenuation"].water.beta_D
    alone = artificial_light(buffers, lamp_params) - buffers.rgb
    both, _ = apply_effects(buffers, chain, np.random.default_rng(0))
    np.testing.assert_allclose(both - buffers.rgb * np.exp(-beta * 3.0), alone, rtol=1e-4, atol=1e-7)


def test_lamp_adds_nothing_outside_its_cone_or_where_there_is_no_surface() -> None:
    buffers = flat_frame(61, 41, 2.0, hfov_deg=110.0)
    rgb = buffers.rgb.copy()
    rgb[:, :5] = 0.5
    ranges = buffers.range_m.copy()
    ranges[:, -5:] = np.inf  # open water on the right
    buffers = buffers_from_range(rgb, ranges, buffers.camera)
    out = artificial_light(buffers, chain_params("artificial_light", lights=(HEADLAMP,)))
    angle = np.degrees(np.arccos(buffers.rays_cam[..., 2]))
    outside = (angle > HEADLAMP.cone_deg) | ~np.isfinite(ranges)
    assert outside.sum() > 100
    np.testing.assert_array_equal(out[outside], buffers.rgb[outside])
    assert np.all(out[angle < 15.0] > buffers.rgb[angle < 15.0])  # inside the fully lit core
    assert np.all(out >= buffers.rgb)


def test_lamp_cone_narrower_than_the_default_edge_is_accepted_from_a_scene_file() -> None:
    narrow = LightSpec(offset_m=(0.0, 0.0, 0.0), cone_deg=5.0)
    params = chain_params("artificial_light", lights=(narrow,))
    buffers = flat_frame(33, 25, 1.0, hfov_deg=60.0)
    out = artificial_light(buffers, params)
    assert out[12, 16, 0] > buffers.rgb[12, 16, 0]  # on axis: lit
    angle = np.degrees(np.arccos(buffers.rays_cam[..., 2]))
    np.testing.assert_array_equal(out[angle > 5.0], buffers.rgb[angle > 5.0])
    with pytest.raises(ConfigError, match="edge_deg"):
        Lamp(edge_deg=-1.0)


# ---------------------------------------------------------------------------------------------- marine snow


def snow_frame(value: float = 1.0, range_m: float = 5.0) -> FrameBuffers:
    return flat_frame(96, 72, range_m, value)


def test_marine_snow_is_deterministic_per_seed() -> None:
    buffers = snow_frame(0.3)
    params = chain_params("marine_snow")
    a = marine_snow(buffers, params, np.random.default_rng(7))
    b = marine_snow(buffers, params, np.random.default_rng(7))
    c = marine_snow(buffers, params, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert not np.array_equal(a, buffers.rgb)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), value=st.sampled_from([0.0, 0.2, 1.0]), lamps=st.booleans(),
       jerlov=st.sampled_from(["I", "II", "9C"]))
def test_marine_snow_only_brightens(seed: int, value: float, lamps: bool, jerlov: str) -> None:
    buffers = snow_frame(value, 3.0)
    lights = {} if lamps else {"lights": ()}  # the scene's default lamps, or none
    params = chain_params("marine_snow", jerlov, effect_params={"marine_snow": {"density_per_m3": 200.0}}, **lights)
    out = marine_snow(buffers, params, np.random.default_rng(seed))
    assert np.all(np.isfinite(out))
    assert np.all(out >= buffers.rgb), "a particle must never darken the scene"
    assert np.any(out > buffers.rgb)


def test_marine_snow_is_hidden_behind_a_close_surface() -> None:
    buffers = snow_frame(0.2, range_m=0.1)  # closer than min_range_m: every particle is behind it
    out = marine_snow(buffers, chain_params("marine_snow", effect_params={"marine_snow": {"density_per_m3": 500.0}}),
                      np.random.default_rng(0))
    np.testing.assert_array_equal(out, buffers.rgb)


def test_marine_snow_particle_count_follows_the_density() -> None:
    buffers = snow_frame()
    params = MarineSnowParams(density_per_m3=50.0, min_range_m=0.5, max_range_m=4.0)
    cam = buffers.camera
    volume = (cam.width / cam.fx) * (cam.height / cam.fy) * (4.0**3 - 0.5**3) / 3.0
    counts = [sample_particles(buffers, params, np.random.default_rng(s)).range_m.size for s in range(40)]
    assert np.mean(counts) == pytest.approx(50.0 * volume, rel=0.1)


def test_marine_snow_refuses_particles_larger_than_its_stamps() -> None:
    with pytest.raises(ConfigError, match="max_radius_px"):
        MarineSnowParams(edge_px=0.5, max_radius_px=15.5)  # would reach 16.75 px: silently dropped before
    MarineSnowParams(edge_px=0.5, max_radius_px=14.75)


# --------------------------------------------------------------------------------------------- motion blur


def test_motion_blur_without_camera_motion_is_the_identity() -> None:
    rgb = textured(321, 241)
    still = Rigid3()
    cases = [
        {"frame_dt_s": 0.1},  # no neighbours
        {"frame_dt_s": 0.1, "T_world_from_cam_prev": still, "T_world_from_cam_next": still},
        {"frame_dt_s": 0.0, "T_world_from_cam_prev": Rigid3(t=[1.0, 0, 0])},  # no timing: no motion
    ]
    params = chain_params("motion_blur")
    for poses in cases:
        buffers = buffers_from_range(rgb, np.full((241, 321), 2.0, np.float32), make_camera(321, 241), **poses)
        np.testing.assert_array_equal(motion_blur(buffers, params), rgb)
    moving = buffers_from_range(rgb, np.full((241, 321), 2.0), make_camera(321, 241), frame_dt_s=0.1,
                                T_world_from_cam_prev=Rigid3(t=[0.1, 0, 0]))
    np.testing.assert_array_equal(motion_blur(moving, MotionBlurParams(shutter_s=0.0)), rgb)


def test_depth_flow_of_an_identity_motion_is_exactly_zero_on_a_large_frame() -> None:
    buffers = flat_frame(1281, 961, 3.0)
    du, dv = depth_flow(buffers, Rigid3())
    assert np.abs(du).max() == 0.0 and np.abs(dv).max() == 0.0


def sideways_frame(range_m: float, shift_m: float = 0.05, width: int = 161, height: int = 121) -> FrameBuffers:
    return buffers_from_range(textured(width, height), np.full((height, width), range_m, np.float32),
                              make_camera(width, height), frame_dt_s=0.1,
                              T_world_from_cam_prev=Rigid3(t=[-shift_m, 0.0, 0.0]),
                              T_world_from_cam_next=Rigid3(t=[shift_m, 0.0, 0.0]))


def test_camera_motion_blurs_along_the_motion() -> None:
    buffers = sideways_frame(1.0)
    out = motion_blur(buffers, chain_params("motion_blur", trajectory=TrajectorySpec(shutter_s=0.05)))
    before_x, after_x = gradient_energy(buffers.rgb, axis=1), gradient_energy(out, axis=1)
    before_y, after_y = gradient_energy(buffers.rgb, axis=0), gradient_energy(out, axis=0)
    assert after_x < 0.5 * before_x, "sideways motion must smear horizontal detail"
    assert after_y / before_y > after_x / before_x, "and smear it more than vertical detail"
    assert out.mean() == pytest.approx(buffers.rgb.mean(), rel=0.02)


def test_motion_blur_parallax_near_blurs_more_than_far_and_infinity_not_at_all() -> None:
    params = chain_params("motion_blur", trajectory=TrajectorySpec(shutter_s=0.05))
    drop = {}
    for r in (1.0, 8.0):
        b = sideways_frame(r)
        drop[r] = gradient_energy(motion_blur(b, params)) / gradient_energy(b.rgb)
    assert drop[1.0] < drop[8.0] < 1.0
    sky = sideways_frame(np.inf)  # pure translation: points at infinity do not move
    np.testing.assert_array_equal(motion_blur(sky, params), sky.rgb)


def test_camera_rotation_blurs_even_open_water() -> None:
    R = Rotation.from_rotvec([0.0, 0.2, 0.0]).as_matrix()
    b = buffers_from_range(textured(161, 121), np.full((121, 161), np.inf), make_camera(161, 121), frame_dt_s=0.1,
                           T_world_from_cam_prev=Rigid3(R.T), T_world_from_cam_next=Rigid3(R))
    out = motion_blur(b, MotionBlurParams(shutter_s=0.05))
    assert gradient_energy(out) < 0.7 * gradient_energy(b.rgb)


# ---------------------------------------------------------------------------------------------- vignetting


@pytest.mark.parametrize("params", [VignettingParams(), VignettingParams(model="poly"),
                                    VignettingParams(model="poly", coeffs=(-0.2, -0.1, 0.0)),
                                    VignettingParams(exponent=2.0)])
def test_vignetting_leaves_the_centre_and_darkens_the_corners(params: VignettingParams) -> None:
    buffers = flat_frame(65, 49, 2.0, value=0.6)
    out = vignetting(buffers, params)
    np.testing.assert_array_equal(out[24, 32], buffers.rgb[24, 32])  # the principal point is pixel (32, 24)
    for v, u in ((0, 0), (0, 64), (48, 0), (48, 64)):
        assert np.all(out[v, u] < 0.6 * 0.9)
    diag = vignetting_gain(buffers.camera, params)[np.arange(24, 49), np.arange(32, 57)]
    assert np.all(np.diff(diag) < 0), "brightness falls monotonically away from the centre"
    assert np.all(out >= 0)


def test_cos4_vignetting_matches_cos_theta_to_the_fourth() -> None:
    cam = make_camera(65, 49)
    gain = vignetting_gain(cam, VignettingParams())
    cos_theta = buffers_from_range(np.zeros((49, 65, 3)), np.ones((49, 65)), cam).rays_cam[..., 2]
    np.testing.assert_allclose(gain, cos_theta**4, rtol=1e-5)
    assert cos_theta.min() < 0.85


# ----------------------------------------------------------------------------------------------- low light


def grey(value: float, n: int = 256) -> FrameBuffers:
    return flat_frame(n, n, 1.0, value)


@pytest.mark.parametrize(("exposure", "gain"), [(0.25, 4.0), (0.5, 1.0), (0.1, 3.0)])
def test_low_light_preserves_the_mean(exposure: float, gain: float) -> None:
    params = LowLightParams(exposure=exposure, gain=gain, bits=None)
    buffers = grey(0.4)
    out = low_light(buffers, params, np.random.default_rng(0))
    mean = gain * exposure * 0.4
    sem = float(noise_std(np.float32(mean), params)) / np.sqrt(out.size)
    assert abs(out.mean() - mean) < 5 * sem + 1e-6


def test_low_light_variance_is_shot_plus_read_noise() -> None:
    params = chain_params("low_light", effect_params={"low_light": {"bits": None, "gain": 8.0, "exposure": 0.1}})
    signals = (0.06, 0.1, 0.3, 0.6, 1.0)  # mean outputs 0.048 ... 0.8: over 5 sigma from 0 and 1, no clipping
    variances = []
    for i, s in enumerate(signals):
        out = low_light(grey(s), params, np.random.default_rng(i))
        mean = params.gain * params.exposure * s
        variances.append(float(out.var()))
        assert variances[-1] == pytest.approx(float(noise_std(np.float32(mean), params)) ** 2, rel=0.03)
    assert np.all(np.diff(variances) > 0), "shot noise grows with the signal"
    floor = params.read_noise_e * params.gain / params.full_well_e
    assert float(noise_std(np.float32(0.0), params)) == pytest.approx(floor, rel=1e-6)
    assert variances[0] > floor**2, "read noise is a floor under the shot noise"
    # Same brightness (gain * exposure = 1), more gain: noisier.
    low_gain = low_light(grey(0.3), LowLightParams(exposure=1.0, gain=1.0, bits=None), np.random.default_rng(0))
    high_gain = low_light(grey(0.3), LowLightParams(exposure=0.125, gain=8.0, bits=None), np.random.default_rng(0))
    assert high_gain.var() > 4 * low_gain.var()


def test_low_light_is_deterministic_clipped_and_quantised() -> None:
    params = chain_params("low_light", effect_params={"low_light": {"gain": 16.0}})
    rgb = np.random.default_rng(0).uniform(0.0, 1.0, (64, 64, 3))
    buffers = buffers_from_range(rgb, np.ones((64, 64)), make_camera(64, 64))
    a = low_light(buffers, params, np.random.default_rng(3))
    np.testing.assert_array_equal(a, low_light(buffers, params, np.random.default_rng(3)))
    assert not np.array_equal(a, low_light(buffers, params, np.random.default_rng(4)))
    assert a.min() >= 0.0 and a.max() <= 1.0 and a.max() == 1.0  # gain 16 x 0.25 saturates the bright half
    np.testing.assert_allclose(a * 255, np.rint(a * 255), atol=1e-4)

"""Tests of the effects pipeline: the registry, ``apply_effects`` and the scene plumbing of ``effects_chain``."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from effects_testdata import make_camera, make_scene

from cadalign.errors import ConfigError
from cadalign.sim.effects import EFFECTS, EffectSpec, FrameBuffers, apply_effects, buffers_from_range
from cadalign.sim.effects.attenuation import AttenuationParams
from cadalign.sim.effects_chain import INJECTED, build_chain, run_chain
from cadalign.sim.spec import LightSpec, TrajectorySpec, WaterSpec
from cadalign.types import Rigid3

PHYSICAL_ORDER = ("artificial_light", "attenuation", "forward_scatter", "backscatter", "marine_snow",
                  "motion_blur", "vignetting", "low_light")






@pytest.fixture
def frame() -> FrameBuffers:
    rng = np.random.default_rng(0)
    ranges = rng.uniform(0.5, 10.0, (24, 32)).astype(np.float32)
    ranges[:4] = np.inf
    return buffers_from_range(rng.uniform(0.0, 1.0, (24, 32, 3)), ranges, make_camera(32, 24), frame_dt_s=0.1,
                              T_world_from_cam_prev=Rigid3(t=[0.02, 0.0, 0.0]))


@pytest.fixture
def recorder(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Replace every registered effect by one that records its name and returns the image unchanged."""
    calls: list[str] = []
    for name, spec in list(EFFECTS.items()):
        def fn(buffers: FrameBuffers, params: object, *rng: object, _name: str = name) -> np.ndarray:
            calls.append(_name)
            return buffers.rgb.copy()

        monkeypatch.setitem(EFFECTS, name, dataclasses.replace(spec, fn=fn))
    return calls


def test_registry_is_in_physical_order() -> None:
    assert tuple(EFFECTS) == PHYSICAL_ORDER
    assert {n for n, s in EFFECTS.items() if s.uses_rng} == {"marine_snow", "low_light"}
    for spec in EFFECTS.values():
        spec.params_type()  # every params field has a default


def test_no_effects_is_the_identity_and_calls_nothing(frame: FrameBuffers, monkeypatch: pytest.MonkeyPatch) -> None:
    def boom(*args: object) -> np.ndarray:
        raise AssertionError("an effect ran although none was listed")

    for name, spec in list(EFFECTS.items()):
        monkeypatch.setitem(EFFECTS, name, dataclasses.replace(spec, fn=boom))
    before = frame.rgb.copy()
    out, timings = apply_effects(frame, [], np.random.default_rng(0))
    assert out is frame.rgb and timings == {}
    np.testing.assert_array_equal(frame.rgb, before)
    empty = make_scene(())
    out, timings = run_chain(build_chain(empty), frame.rgb, None, empty, 0, Rigid3(), frame.camera)
    assert out is frame.rgb and timings == {}


def test_unknown_effect_raises_config_error_naming_the_allowed_ones(frame: FrameBuffers) -> None:
    with pytest.raises(ConfigError, match="fog") as err:
        apply_effects(frame, [("attenuation", None), ("fog", None)], np.random.default_rng(0))
    assert all(name in str(err.value) for name in EFFECTS)
    with pytest.raises(ConfigError, match="fog") as err:
        build_chain(make_scene(("fog",)), source="scene.toml")
    assert "scene.toml" in str(err.value) and all(name in str(err.value) for name in EFFECTS)


def test_repeated_effect_or_wrong_params_type_raise(frame: FrameBuffers) -> None:
    with pytest.raises(ConfigError, match="twice"):
        apply_effects(frame, [("vignetting", None), ("vignetting", None)], np.random.default_rng(0))
    with pytest.raises(ConfigError, match="AttenuationParams"):
        apply_effects(frame, [("backscatter", AttenuationParams())], np.random.default_rng(0))


def test_effects_run_in_physical_order_whatever_the_list_order(frame: FrameBuffers, recorder: list[str]) -> None:
    listed = list(reversed(PHYSICAL_ORDER))
    _, timings = apply_effects(frame, [(n, None) for n in listed], np.random.default_rng(0))
    assert recorder == list(PHYSICAL_ORDER)
    assert list(timings) == list(PHYSICAL_ORDER) and all(t >= 0 for t in timings.values())


def test_only_listed_effects_run(frame: FrameBuffers, recorder: list[str]) -> None:
    apply_effects(frame, [("vignetting", None), ("attenuation", None)], np.random.default_rng(0))
    assert recorder == ["attenuation", "vignetting"]


def test_each_effect_sees_the_previous_output(frame: FrameBuffers, monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[float] = []
    for name, spec in list(EFFECTS.items()):
        def fn(buffers: FrameBuffers, params: object, *rng: object) -> np.ndarray:
            seen.append(float(buffers.rgb[0, 0, 0]))
            return buffers.rgb + np.float32(1.0)

        monkeypatch.setitem(EFFECTS, name, EffectSpec(spec.params_type, fn, spec.uses_rng))
    out, _ = apply_effects(frame, [("attenuation", None), ("vignetting", None), ("backscatter", None)],
                           np.random.default_rng(0))
    start = float(frame.rgb[0, 0, 0])
    assert seen == [start, start + 1, start + 2]
    assert out.max() <= 1.0  # the sensor saturates: output clipped to [0, 1]


def test_build_chain_injects_the_scene_physics_into_every_effect() -> None:
    lamp = LightSpec(offset_m=(0.1, 0.0, 0.0), intensity=12.0, cone_deg=25.0)
    spec = make_scene(PHYSICAL_ORDER, water=WaterSpec(jerlov="3C"), lights=(lamp,), ambient=0.5,
                      trajectory=TrajectorySpec(shutter_s=0.03))
    chain = dict(build_chain(spec))
    assert list(chain) == list(PHYSICAL_ORDER)
    waters = [p.water for p in chain.values() if hasattr(p, "water")]
    assert len(waters) == 4 and all(w is waters[0] for w in waters)
    for name in ("artificial_light", "marine_snow"):
        (got,) = chain[name].lamps
        assert (got.offset_m, got.intensity, got.cone_deg) == (lamp.offset_m, 12.0, 25.0)
        assert chain[name].ambient == 0.5
    assert chain["motion_blur"].shutter_s == 0.03
    explicit = WaterSpec(beta_D=(0.3, 0.1, 0.05), beta_B=(0.4, 0.2, 0.1), B_inf=(0.0, 0.1, 0.2))
    water = dict(build_chain(make_scene(("attenuation",), water=explicit)))["attenuation"].water
    np.testing.assert_allclose(water.beta_D, (0.3, 0.1, 0.05), rtol=1e-6)


@pytest.mark.parametrize("key", INJECTED)
def test_effect_params_may_not_override_the_scene_physics(key: str) -> None:
    owner = {"water": "attenuation", "lamps": "artificial_light", "ambient": "marine_snow", "shutter_s": "motion_blur"}
    spec = make_scene((owner[key],), effect_params={owner[key]: {key: 1}})
    with pytest.raises(ConfigError, match=key):
        build_chain(spec)


def test_run_chain_is_deterministic_per_frame() -> None:
    spec = make_scene(("marine_snow", "low_light"), trajectory=TrajectorySpec(fps=10.0))
    chain = build_chain(spec)
    buffers = buffers_from_range(np.full((24, 32, 3), 0.3), np.full((24, 32), 3.0), make_camera(32, 24))
    gt = SimpleNamespace(depth_m=buffers.depth_m, range_m=buffers.range_m, rays_cam=buffers.rays_cam,
                         normals_cam=buffers.normals_cam)
    a, _ = run_chain(chain, buffers.rgb, gt, spec, 3, Rigid3(), buffers.camera)
    b, _ = run_chain(chain, buffers.rgb, gt, spec, 3, Rigid3(), buffers.camera)
    c, _ = run_chain(chain, buffers.rgb, gt, spec, 4, Rigid3(), buffers.camera)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.all(np.isfinite(a)) and a.min() >= 0 and a.max() <= 1

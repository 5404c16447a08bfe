"""Turn a scene spec into the chain of declared effects and run it on rendered frames.

Only effects listed in the scene's ``effects`` appear in the chain, so an
undeclared effect is never called. Shared physical settings (water, lamps,
ambient level, shutter time) are injected from the scene so they cannot
disagree between effects.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from cadalign.config import from_dict
from cadalign.errors import ConfigError
from cadalign.sim.effects import EFFECTS, FrameBuffers, Lamp, WaterParams, apply_effects, water_from_jerlov
from cadalign.sim.scene_spec import SceneSpec
from cadalign.sim.trajectory import pose_at
from cadalign.types import Rigid3

INJECTED = ("water", "lamps", "ambient", "shutter_s")
Chain = list[tuple[str, Any]]


def water_params(spec: SceneSpec) -> WaterParams:
    w = spec.water
    explicit = (w.beta_D, w.beta_B, w.B_inf)
    if all(v is None for v in explicit):
        return water_from_jerlov(w.jerlov)
    if any(v is None for v in explicit):
        raise ConfigError("[water]: give all of beta_D, beta_B and B_inf, or none of them (to use jerlov)")
    return WaterParams(np.array(w.beta_D), np.array(w.beta_B), np.array(w.B_inf))


def build_chain(spec: SceneSpec, source: str = "<scene>") -> Chain:
    """``(name, params)`` for each declared effect; raises ConfigError on unknown names or bad tables."""
    unknown = [e for e in spec.effects if e not in EFFECTS]
    if unknown:
        raise ConfigError(f"{source}: unknown effect(s) {unknown} in 'effects'; allowed values: {', '.join(EFFECTS)}")
    stray = [k for k in spec.effect_params if k not in spec.effects]
    if stray:
        raise ConfigError(f"{source}: effect_params for {stray}, which are not in 'effects' {list(spec.effects)}")
    shared = {
        "water": water_params(spec),
        "lamps": tuple(Lamp(lt.offset_m, lt.direction, lt.intensity, lt.cone_deg) for lt in spec.lights),
        "ambient": spec.ambient,
        "shutter_s": spec.trajectory.shutter_s,
    }
    chain: Chain = []
    for name in spec.effects:
        params_type = EFFECTS[name].params_type
        table = dict(spec.effect_params.get(name, {}))
        clash = [k for k in INJECTED if k in table]
        if clash:
            raise ConfigError(f"{source}: effect_params.{name} sets {clash}; set these in [water], [[lights]], "
                              "'ambient' and [trajectory] instead")
        params = from_dict(params_type, table, source=f"{source} [effect_params.{name}]")
        names = {f.name for f in dataclasses.fields(params_type)}
        params = dataclasses.replace(params, **{k: v for k, v in shared.items() if k in names})
        chain.append((name, params))
    return chain


def run_chain(chain: Chain, clean: np.ndarray, gt: Any, spec: SceneSpec, k: int,
              T_world_from_cam: Rigid3, camera: Any) -> tuple[np.ndarray, dict[str, float]]:
    """Apply ``chain`` to frame ``k``'s clean render; random effects draw from a per-frame seed."""
    if not chain:
        return clean, {}
    traj = spec.trajectory
    dt = 1.0 / traj.fps
    buffers = FrameBuffers(
        rgb=clean, depth_m=gt.depth_m, range_m=gt.range_m, rays_cam=gt.rays_cam, normals_cam=gt.normals_cam,
        camera=camera, T_world_from_cam=T_world_from_cam,
        T_world_from_cam_prev=pose_at(traj, (k - 1) * dt, spec.seed),
        T_world_from_cam_next=pose_at(traj, (k + 1) * dt, spec.seed), frame_dt_s=dt,
    )
    rng = np.random.default_rng([spec.seed, k, 0xC0FFEE])
    return apply_effects(buffers, chain, rng)

"""Small builders shared by the water-effect tests: a pinhole camera and a one-box scene spec."""

from __future__ import annotations

import numpy as np

from cadalign.sim.effects_chain import build_chain
from cadalign.sim.spec import ObjectSpec, SceneSpec, WaterSpec
from cadalign.types import Camera


def make_camera(width: int, height: int, hfov_deg: float = 70.0) -> Camera:
    """Pinhole camera with the principal point at the image centre (odd sizes: on a pixel centre)."""
    fx = width / 2 / np.tan(np.radians(hfov_deg / 2))
    return Camera(np.array([[fx, 0.0, width / 2], [0.0, fx, height / 2], [0.0, 0.0, 1.0]]), width, height)


def make_scene(effects: tuple[str, ...], jerlov: str = "II", **kw: object) -> SceneSpec:
    """A one-box scene declaring ``effects`` in Jerlov water ``jerlov`` (``water=`` in ``kw`` wins)."""
    kw.setdefault("water", WaterSpec(jerlov=jerlov))
    return SceneSpec(name="t", objects=(ObjectSpec(name="box", source="procedural:box"),), effects=effects, **kw)


def chain_params(name: str, jerlov: str = "II", **kw: object) -> object:
    """The params ``build_chain`` makes for one effect of a scene in the given water."""
    return dict(build_chain(make_scene((name,), jerlov, **kw)))[name]

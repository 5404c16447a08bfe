"""Procedural subsea parts: a Xmas-tree frame, four valve types and a hot stab.

Sizes follow the thesis scene: frame 9×10×6 m, valves about 0.5×0.7×0.5 m,
hot stabs about 0.05×0.75×0.3 m. Each builder returns a watertight-ish
``trimesh.Trimesh`` in metres in the part's own frame (z up, origin at the
centre of the base), scaled to ``size_m`` when given.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import trimesh
from scipy.ndimage import zoom

DEFAULT_SIZES_M: dict[str, tuple[float, float, float]] = {
    "frame": (9.0, 10.0, 6.0),
    "valve_a": (0.5, 0.7, 0.5),
    "valve_b": (0.5, 0.7, 0.5),
    "valve_c": (0.5, 0.7, 0.5),
    "valve_d": (0.5, 0.7, 0.5),
    "hot_stab": (0.05, 0.75, 0.3),
    "box": (1.0, 1.0, 1.0),
    "cylinder": (1.0, 1.0, 1.0),
}


def _box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents, transform=trimesh.transformations.translation_matrix(centre))


def _cyl(radius: float, length: float, centre: tuple[float, float, float], axis: str = "z") -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius=radius, height=length, sections=24)
    rot = {"z": np.eye(4), "x": trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]),
           "y": trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])}[axis]
    m.apply_transform(rot)
    m.apply_translation(centre)
    return m


def frame() -> trimesh.Trimesh:
    """A Xmas-tree protection frame: posts, three levels of beams, braces and a central tree body."""
    w, d, h, b = 9.0, 10.0, 6.0, 0.3
    parts = []
    for x in (-w / 2 + b / 2, w / 2 - b / 2):
        for y in (-d / 2 + b / 2, d / 2 - b / 2):
            parts.append(_box((b, b, h), (x, y, h / 2)))
    for z in (b / 2, h / 2, h - b / 2):
        for y in (-d / 2 + b / 2, d / 2 - b / 2):
            parts.append(_box((w, b, b), (0, y, z)))
        for x in (-w / 2 + b / 2, w / 2 - b / 2):
            parts.append(_box((b, d, b), (x, 0, z)))
    parts.append(_box((w, b, b), (0, 0, h / 2)))  # a middle cross beam carrying valves
    parts.append(_cyl(0.45, 5.0, (0, 0, 2.5)))  # the tree body
    parts.append(_box((2.0, 2.0, 0.4), (0, 0, 0.2)))  # its base
    parts.append(_cyl(0.25, 3.5, (0, 1.75, 3.8), axis="y"))  # a flowline spool
    return trimesh.util.concatenate(parts)


def valve(kind: str) -> trimesh.Trimesh:
    """One of four valve designs, about 0.5×0.7×0.5 m, flow axis along y."""
    flanges = [_cyl(0.14, 0.05, (0, y, 0.2), axis="y") for y in (-0.325, 0.325)]
    pipe = _cyl(0.08, 0.7, (0, 0, 0.2), axis="y")
    if kind == "valve_a":  # gate valve with a hand wheel
        body = [_box((0.4, 0.35, 0.3), (0, 0, 0.15)), _cyl(0.03, 0.12, (0, 0, 0.36))]
        wheel = trimesh.creation.torus(0.17, 0.025, major_sections=24, minor_sections=8)
        wheel.apply_translation((0, 0, 0.44))
        extra = [wheel, _box((0.34, 0.03, 0.03), (0, 0, 0.44)), _box((0.03, 0.34, 0.03), (0, 0, 0.44))]
    elif kind == "valve_b":  # ball valve with a lever
        body = [trimesh.creation.icosphere(subdivisions=2, radius=0.2)]
        body[0].apply_translation((0, 0, 0.2))
        extra = [_cyl(0.03, 0.15, (0, 0, 0.42)), _box((0.5, 0.06, 0.04), (0.1, 0, 0.48))]
    elif kind == "valve_c":  # actuated valve: bonnet and a cylindrical actuator
        body = [_box((0.32, 0.32, 0.28), (0, 0, 0.14)), _cyl(0.12, 0.08, (0, 0, 0.32))]
        extra = [_cyl(0.2, 0.14, (0, 0, 0.43))]
    elif kind == "valve_d":  # ROV class-4 valve with a paddle handle and a bucket
        body = [_box((0.45, 0.3, 0.26), (0, 0, 0.13)), _cyl(0.1, 0.14, (0, 0, 0.33))]
        extra = [_box((0.06, 0.22, 0.1), (0, 0, 0.45))]
    else:
        raise ValueError(f"unknown valve kind {kind!r}; allowed: valve_a, valve_b, valve_c, valve_d")
    return trimesh.util.concatenate([*flanges, pipe, *body, *extra])


def hot_stab() -> trimesh.Trimesh:
    """A hot stab: a stepped probe along y with a T-handle, 0.05×0.75×0.3 m."""
    parts = [
        _cyl(0.018, 0.3, (0, 0.225, 0.025), axis="y"),  # nose
        _cyl(0.025, 0.3, (0, -0.075, 0.025), axis="y"),  # body
        _box((0.05, 0.05, 0.05), (0, -0.25, 0.025)),  # collar
        _box((0.03, 0.04, 0.25), (0, -0.3, 0.175)),  # handle post
        _box((0.05, 0.15, 0.04), (0, -0.3, 0.28)),  # handle grip
    ]
    return trimesh.util.concatenate(parts)


BUILDERS: dict[str, Callable[[], trimesh.Trimesh]] = {
    "frame": frame,
    "valve_a": lambda: valve("valve_a"),
    "valve_b": lambda: valve("valve_b"),
    "valve_c": lambda: valve("valve_c"),
    "valve_d": lambda: valve("valve_d"),
    "hot_stab": hot_stab,
    "box": lambda: _box((1.0, 1.0, 1.0), (0, 0, 0.5)),
    "cylinder": lambda: _cyl(0.5, 1.0, (0, 0, 0.5)),
}


def make_part(kind: str, size_m: tuple[float, float, float] | None = None) -> trimesh.Trimesh:
    """Build procedural part ``kind``, optionally rescaled per axis so its bounding box is ``size_m``."""
    if kind not in BUILDERS:
        raise ValueError(f"unknown procedural part {kind!r}; allowed: {', '.join(BUILDERS)}")
    mesh = BUILDERS[kind]()
    if size_m is not None:
        extent = mesh.bounds[1] - mesh.bounds[0]
        scale = np.asarray(size_m, dtype=float) / np.maximum(extent, 1e-9)
        mesh.apply_transform(np.diag([*scale, 1.0]))
    return mesh


def seabed(size_m: float, relief_m: float, seed: int, cells: int = 96) -> trimesh.Trimesh:
    """A square seabed patch at z ≈ 0 with smooth random relief (grid of ``cells``²×2 triangles)."""
    rng = np.random.default_rng(seed)
    n = cells + 1
    xs = np.linspace(-size_m / 2, size_m / 2, n)
    xx, yy = np.meshgrid(xs, xs)
    coarse = rng.standard_normal((7, 7))

    zz = zoom(coarse, n / 7, order=3)[:n, :n] * relief_m
    # keep the ground flat under the structure (|x|,|y| < 6 m) so parts sit on it
    flat = np.clip((np.maximum(np.abs(xx), np.abs(yy)) - 6.0) / 3.0, 0, 1)
    zz = zz * flat
    verts = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    return trimesh.Trimesh(verts, faces, process=False)

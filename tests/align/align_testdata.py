"""Synthetic SfM clouds of a subsea structure with a known Sim3 (imported by the align tests).

The "structure" is the procedural Xmas-tree frame (9x10x6 m) with four valves posed on it, like the
default scene. The "SfM cloud" is: points sampled on the structure surface, seabed clutter with no CAD
counterpart, Gaussian noise and a few gross outliers, all mapped by ``sfm_from_cad`` (a random Sim3) into
an arbitrary SfM frame and unit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from cadalign.cad import CadModel
from cadalign.cad.procedural import make_part
from cadalign.geometry import random_rotation
from cadalign.types import Rigid3, Sim3

#: (part, position in metres, yaw in degrees) of the valves on the frame, as in the default scene.
VALVES = (
    ("valve_a", (-2.5, 0.0, 3.15), 0.0),
    ("valve_b", (2.4, 0.0, 3.15), 90.0),
    ("valve_c", (1.8, -4.85, 0.3), 90.0),
    ("valve_a", (-4.35, 2.0, 3.15), 0.0),
)


def _yaw(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def model_of(mesh: trimesh.Trimesh, name: str) -> CadModel:
    return CadModel(name, np.asarray(mesh.vertices), np.asarray(mesh.faces))


def structure_parts() -> list[tuple[CadModel, Rigid3]]:
    """The frame and its valves as (model in its own frame, world_from_part) pairs, metres."""
    parts = [(model_of(make_part("frame"), "frame"), Rigid3())]
    for i, (kind, pos, yaw) in enumerate(VALVES):
        parts.append((model_of(make_part(kind), f"{kind}_{i}"), Rigid3(_yaw(yaw), pos)))
    return parts


def structure_mesh(parts: list[tuple[CadModel, Rigid3]] | None = None) -> trimesh.Trimesh:
    """All parts posed in the world frame, as one mesh (metres)."""
    meshes = []
    for model, T in parts or structure_parts():
        meshes.append(trimesh.Trimesh(T.apply(model.vertices_m), model.faces, process=False))
    return trimesh.util.concatenate(meshes)


def random_sim3(rng: np.random.Generator, scale_range: tuple[float, float] = (0.05, 20.0)) -> Sim3:
    """A random similarity: log-uniform scale, Haar rotation, translation up to 100 per axis."""
    s = float(np.exp(rng.uniform(np.log(scale_range[0]), np.log(scale_range[1]))))
    return Sim3(s, random_rotation(rng), rng.uniform(-100.0, 100.0, 3))


@dataclass(frozen=True)
class SyntheticCloud:
    """An SfM-like cloud and its ground truth.

    Attributes:
        points_sfm: (N, 3) points in the SfM frame (arbitrary unit).
        points_world_m: (N, 3) the same points in the world (CAD) frame, metres.
        on_structure: (N,) True for points sampled on the CAD surface (before noise).
        cad_from_sfm: the true similarity mapping SfM coordinates to world metres.
    """

    points_sfm: np.ndarray
    points_world_m: np.ndarray
    on_structure: np.ndarray
    cad_from_sfm: Sim3


def make_cloud(
    seed: int,
    *,
    n_structure: int = 6000,
    clutter_frac: float = 0.45,
    outlier_frac: float = 0.03,
    noise_m: float = 0.015,
    seabed_half_m: float = 12.0,
    sfm_from_cad: Sim3 | None = None,
    mesh: trimesh.Trimesh | None = None,
) -> SyntheticCloud:
    """Sample a synthetic SfM cloud of the structure (see the module docstring).

    ``clutter_frac`` and ``outlier_frac`` are fractions of the whole cloud; seabed points lie on
    ``z = 0`` (with 5 cm roughness) in a square of half-size ``seabed_half_m`` around the structure.
    """
    rng = np.random.default_rng(seed)
    mesh = mesh if mesh is not None else structure_mesh()
    on, _ = trimesh.sample.sample_surface(mesh, n_structure, seed=seed)
    n_total = int(round(n_structure / (1.0 - clutter_frac - outlier_frac)))
    n_clutter = int(round(clutter_frac * n_total))
    n_out = n_total - n_structure - n_clutter
    bed = np.column_stack([rng.uniform(-seabed_half_m, seabed_half_m, (n_clutter, 2)),
                           rng.normal(0.0, 0.05, n_clutter)])
    lo, hi = mesh.bounds[0] - 3.0, mesh.bounds[1] + 3.0
    gross = rng.uniform(lo, hi, (n_out, 3))
    world = np.concatenate([on, bed, gross]) + rng.normal(0.0, noise_m, (n_total, 3)) * np.r_[
        np.ones(n_structure + n_clutter), np.zeros(n_out)][:, None]
    mask = np.r_[np.ones(n_structure, bool), np.zeros(n_total - n_structure, bool)]
    perm = rng.permutation(n_total)
    world, mask = world[perm], mask[perm]
    sfm_from_cad = sfm_from_cad if sfm_from_cad is not None else random_sim3(rng)
    return SyntheticCloud(sfm_from_cad.apply(world), world, mask, sfm_from_cad.inverse())


def sim3_errors(est: Sim3, gt: Sim3, points_sfm: np.ndarray | None = None) -> tuple[float, float, float]:
    """(rotation error in degrees, translation error in metres, relative scale error) of ``cad_from_sfm``.

    The translation error is measured where it matters: the largest displacement of the SfM points'
    centroid region, i.e. ``|est(c) - gt(c)|`` at the centroid ``c`` of ``points_sfm`` (the raw ``t``
    depends on where the SfM origin happens to be, up to 100 units away).
    """
    dR = est.R @ gt.R.T
    rot_deg = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0))))
    c = np.zeros(3) if points_sfm is None else np.mean(points_sfm, axis=0)
    trans_m = float(np.linalg.norm(est.apply(c[None])[0] - gt.apply(c[None])[0]))
    return rot_deg, trans_m, abs(est.s / gt.s - 1.0)


def default_scene_parts() -> tuple[list[tuple[CadModel, Rigid3]], trimesh.Trimesh]:
    """The objects of the default simulator scene (``datasets/scenes/default.toml``) as posed CAD parts,
    and its seabed mesh (world metres). Needs the shared UUV CAD data for the BOP panel."""
    from cadalign.sim.scene import build_scene
    from cadalign.sim.spec import default_scene_path, load_scene

    path = default_scene_path()
    scene = build_scene(load_scene(path), path)
    parts = [(model_of(o.mesh, o.name), o.T_world_from_obj) for o in scene.objects]
    return parts, scene.seabed


def make_scene_cloud(seed: int, parts, seabed: trimesh.Trimesh, *, n_structure: int = 6000,
                     clutter_frac: float = 0.45, outlier_frac: float = 0.03, noise_m: float = 0.015,
                     seabed_half_m: float = 12.0, sfm_from_cad: Sim3 | None = None) -> SyntheticCloud:
    """Like :func:`make_cloud`, with the clutter sampled on a real seabed mesh (relief) around the structure."""
    rng = np.random.default_rng(seed)
    mesh = structure_mesh(parts)
    centres = seabed.triangles_center
    near = np.all(np.abs(centres[:, :2]) < seabed_half_m, axis=1)
    bed_mesh = seabed.submesh([np.flatnonzero(near)], append=True)
    on, _ = trimesh.sample.sample_surface(mesh, n_structure, seed=seed)
    n_total = int(round(n_structure / (1.0 - clutter_frac - outlier_frac)))
    n_clutter = int(round(clutter_frac * n_total))
    bed, _ = trimesh.sample.sample_surface(bed_mesh, n_clutter, seed=seed + 1)
    n_out = n_total - n_structure - n_clutter
    gross = rng.uniform(mesh.bounds[0] - 3.0, mesh.bounds[1] + 3.0, (n_out, 3))
    noisy = np.concatenate([on, bed]) + rng.normal(0.0, noise_m, (n_structure + n_clutter, 3))
    world = np.concatenate([noisy, gross])
    mask = np.r_[np.ones(n_structure, bool), np.zeros(n_total - n_structure, bool)]
    perm = rng.permutation(n_total)
    world, mask = world[perm], mask[perm]
    sfm_from_cad = sfm_from_cad if sfm_from_cad is not None else random_sim3(rng)
    return SyntheticCloud(sfm_from_cad.apply(world), world, mask, sfm_from_cad.inverse())

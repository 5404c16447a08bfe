"""The seabed under a structure from SfM points: found and placed when the points off the CAD lie on a
floor, refused when they do not (points in the water, a plane above a camera), and as an occluder it hides
the buried part of the structure from the visible masks."""

from __future__ import annotations

import numpy as np
import trimesh

from cadalign.align.seabed import SeabedConfig, fit_seabed
from cadalign.raycast.core import RaycastRenderer, RenderMesh
from cadalign.types import Camera, Rigid3


def _scene(seed: int = 0, tilt_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 2x1.4x1.2 m block sunk 0.3 m into a (tilted) floor, SfM-like points on the floor and the block,
    and cameras on a ring above: (points, their distance to the CAD, CAD vertices, camera centres)."""
    rng = np.random.default_rng(seed)
    block = trimesh.creation.box(extents=[2.0, 1.4, 1.2])
    V = np.asarray(block.vertices) + [0, 0, 0.3]
    floor = np.c_[rng.uniform(-4, 4, (600, 2)), rng.normal(0, 0.01, 600)]
    floor = floor[~((np.abs(floor[:, 0]) < 1.0) & (np.abs(floor[:, 1]) < 0.7))]  # not under the block
    on_block = np.c_[rng.uniform(-1, 1, 200), np.full(200, -0.7), rng.uniform(0, 0.9, 200)]
    t = np.radians(tilt_deg)
    R = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    P = np.concatenate([floor, on_block]) @ R.T
    dist = np.r_[np.full(len(floor), 0.5), np.zeros(len(on_block))]
    a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    cams = np.c_[5 * np.cos(a), 5 * np.sin(a), np.full(12, 3.0)] @ R.T
    return P, dist, V @ R.T, cams


def test_a_floor_under_a_sunk_block_is_found_where_it_is() -> None:
    for tilt in (0.0, 20.0):
        P, dist, V, cams = _scene(tilt_deg=tilt)
        sea = fit_seabed(P, dist, V, cams, SeabedConfig())
        assert sea is not None
        up = np.array([0.0, -np.sin(np.radians(tilt)), np.cos(np.radians(tilt))])
        assert np.degrees(np.arccos(abs(sea.normal @ up))) < 1.0 and abs(sea.offset) < 0.01
        assert sea.normal @ up > 0  # towards the cameras
        assert abs(sea.summary["cad_lowest_above_m"] + 0.3) < 0.02  # 0.3 m of the block below the floor
        assert np.allclose(sea.vertices @ sea.normal - sea.offset, 0.0, atol=1e-9)


def test_no_floor_from_points_in_the_water_or_above_a_camera() -> None:
    P, dist, V, cams = _scene()
    rng = np.random.default_rng(1)
    cloud = rng.uniform(-4, 4, (600, 3))  # marine snow, fish: no plane
    assert fit_seabed(cloud, np.full(600, 0.5), V, cams, SeabedConfig()) is None
    low = cams.copy()
    low[0, 2] = -1.0  # one camera under the "floor": it is no floor
    assert fit_seabed(P, dist, V, low, SeabedConfig()) is None
    assert fit_seabed(P, dist, V, cams, SeabedConfig(enabled=False)) is None
    assert fit_seabed(P[:10], dist[:10], V, cams, SeabedConfig()) is None  # too few points


def test_the_floor_hides_the_buried_part_from_the_visible_mask() -> None:
    P, dist, V, cams = _scene()
    sea = fit_seabed(P, dist, V, cams, SeabedConfig())
    assert sea is not None
    block = trimesh.creation.box(extents=[2.0, 1.4, 1.2])
    mesh = RenderMesh(np.asarray(block.vertices) + [0, 0, 0.3], np.asarray(block.faces), 1, 1)
    cam = Camera(np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]]), 160, 120)
    eye = np.array([5.0, 1.0, 1.5])  # above the floor, looking down at the block's side
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    T = Rigid3(np.stack([x, np.cross(z, x), z], axis=1), eye)
    alone = RaycastRenderer([mesh], cam).render(T)
    floored = RaycastRenderer([mesh, RenderMesh(sea.vertices, sea.faces, 0, 0)], cam).render(T)
    # a block pixel stays visible exactly when its surface point is above the floor (z > 0)
    hit = T.apply(alone.rays_cam * np.where(np.isfinite(alone.range_m), alone.range_m, 0)[..., None])
    block = alone.instance == 1
    above, below = block & (hit[..., 2] > 0.02), block & (hit[..., 2] < -0.02)
    assert below.sum() > 200 and above.sum() > 1000
    assert np.all(floored.instance[above] == 1) and not np.any(floored.instance[below] == 1)
    assert np.array_equal(floored.full_masks[1], alone.full_masks[1])  # the full mask ignores occluders

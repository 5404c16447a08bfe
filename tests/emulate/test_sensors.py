"""LiDAR, sonar and novel views: exact answers in a box room, seeded noise, agreement with the GT caster."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cadalign.emulate import lidar, sonar, views
from cadalign.emulate.mesh import LayeredMesh
from cadalign.errors import ConfigError
from cadalign.types import Rigid3


def _room(half: float = 5.0) -> LayeredMesh:
    """A closed cube [-half, half]^3: floor (z = -half) class 0, everything else class 1, part = face % 7."""
    box = trimesh.creation.box(extents=(2 * half,) * 3)
    n = len(box.faces)
    floor = np.asarray(box.triangles_center)[:, 2] < -half + 1e-9
    return LayeredMesh(box.vertices, box.faces, np.tile([10, 20, 30], (n, 1)), np.where(floor, 0, 1),
                       np.arange(n) % 7, np.zeros(n), class_names=("background", "wall"))


def test_spinning_pattern_and_exact_ranges_in_a_room() -> None:
    cfg = lidar.LidarConfig(channels=8, vfov_deg=(-20.0, 20.0), horizontal_res_deg=5.0, range_noise_m=0.0)
    d, ring, az, el = lidar.scan_directions(cfg)
    assert len(d) == 8 * 72 and ring.max() == 7 and np.allclose(np.linalg.norm(d, axis=1), 1)
    np.testing.assert_allclose(np.degrees(el[:8]), np.linspace(-20, 20, 8))
    s = lidar.scan(_room(), Rigid3(), cfg)
    assert len(s.range_m) == s.n_rays == 8 * 72  # a closed room returns every ray
    # exact: the first wall each beam meets is at 5 m along the dominant axis of its direction
    dirs = np.stack([np.cos(s.elevation_rad) * np.cos(s.azimuth_rad), np.cos(s.elevation_rad) * np.sin(s.azimuth_rad),
                     np.sin(s.elevation_rad)], 1)
    np.testing.assert_array_less(np.abs(s.range_m - 5.0 / np.abs(dirs).max(1)), 1e-5)
    np.testing.assert_allclose(np.abs(s.xyz_world).max(1), 5.0, atol=1e-5)
    assert set(np.unique(s.class_id)) == {1} and np.all(s.rgb == [10, 20, 30])


def test_noise_dropout_range_limits_and_seeds() -> None:
    room = _room()
    base = {"channels": 16, "horizontal_res_deg": 1.0, "pattern": "spinning"}
    exact = lidar.scan(room, Rigid3(), lidar.LidarConfig(**base, range_noise_m=0.0))
    noisy = lidar.scan(room, Rigid3(), lidar.LidarConfig(**base, range_noise_m=0.05, seed=3))
    again = lidar.scan(room, Rigid3(), lidar.LidarConfig(**base, range_noise_m=0.05, seed=3))
    other = lidar.scan(room, Rigid3(), lidar.LidarConfig(**base, range_noise_m=0.05, seed=4))
    err = noisy.range_m - exact.range_m
    assert abs(err.std() - 0.05) < 0.005 and abs(err.mean()) < 0.005
    np.testing.assert_array_equal(noisy.range_m, again.range_m)
    assert not np.array_equal(noisy.range_m, other.range_m)
    drop = lidar.scan(room, Rigid3(), lidar.LidarConfig(**base, range_noise_m=0.0, dropout=0.3))
    assert abs(1 - len(drop.range_m) / exact.n_rays - 0.3) < 0.03
    near = lidar.scan(room, Rigid3(), lidar.LidarConfig(**base, range_noise_m=0.0, max_range_m=5.5))
    assert np.all(near.range_m <= 5.5) and 0 < len(near.range_m) < exact.n_rays
    with pytest.raises(ConfigError, match="min_range_m"):
        lidar.LidarConfig(min_range_m=10.0, max_range_m=5.0)


def test_uniform_sphere_is_uniform() -> None:
    d = lidar.uniform_sphere(200_000, np.random.default_rng(0))
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.abs(d.mean(0)).max() < 0.01
    hist = np.histogram(d[:, 2], bins=10, range=(-1, 1))[0] / len(d)  # Archimedes: z is uniform
    assert np.abs(hist - 0.1).max() < 0.005
    s = lidar.scan(_room(), Rigid3(), lidar.LidarConfig(pattern="sphere", n_rays=2000, range_noise_m=0.0))
    assert len(s.range_m) == 2000 and np.all(s.ring == -1)


def test_lidar_files_round_trip(tmp_path) -> None:
    s = lidar.scan(_room(), Rigid3(), lidar.LidarConfig(channels=4, horizontal_res_deg=10.0))
    with np.load(lidar.write_npz(s, tmp_path / "s.npz")) as z:
        np.testing.assert_array_equal(z["xyz_world"], s.xyz_world)
        np.testing.assert_array_equal(z["class_id"], s.class_id)
    pc = trimesh.load(lidar.write_ply(s, tmp_path / "s.ply"))
    np.testing.assert_allclose(np.asarray(pc.vertices), s.xyz_world)


def _floor_sonar(cfg: sonar.SonarConfig) -> sonar.SonarImage:
    floor = LayeredMesh(np.array([[-100.0, -100, 0], [100, -100, 0], [100, 100, 0], [-100, 100, 0]]),
                        np.array([[0, 1, 2], [0, 2, 3]]), np.zeros((2, 3)), np.zeros(2), np.zeros(2), np.zeros(2))
    pitch = np.radians(30.0)  # looking 30 degrees down from 5 m above the floor
    R = np.array([[np.cos(pitch), 0, np.sin(pitch)], [0, 1, 0], [-np.sin(pitch), 0, np.cos(pitch)]])
    return sonar.ping(floor, Rigid3(R, [0.0, 0.0, 5.0]), cfg)


def test_sonar_geometry_incidence_attenuation_and_speckle() -> None:
    cfg = sonar.SonarConfig(n_beams=9, hfov_deg=40.0, vfov_deg=20.0, elevation_samples=64, max_range_m=30.0,
                            range_bins=300, speckle_looks=0.0, noise_floor=0.0, attenuation_db_per_m=0.0,
                            class_reflectivity=(1.0,))
    img = _floor_sonar(cfg)
    centre = img.clean[:, 4]
    on = np.flatnonzero(centre > 0)
    # the central beam's fan meets the floor between 5/sin(40 deg) and 5/sin(20 deg)
    assert img.ranges_m[on].min() == pytest.approx(5 / np.sin(np.radians(40)), abs=0.15)
    assert img.ranges_m[on].max() == pytest.approx(5 / np.sin(np.radians(20)), abs=0.15)
    assert np.all(img.class_id[centre > 0, 4] == 0) and np.all(img.class_id[centre == 0, 4] == -1)
    near = centre[on[: len(on) // 4]].mean()
    far = centre[on[-len(on) // 4:]].mean()
    assert near > far  # steeper incidence near the sonar backscatters more
    atten = _floor_sonar(cfg.__class__(**{**cfg.__dict__, "attenuation_db_per_m": 0.5}))
    ratio = atten.clean[on, 4] / centre[on]
    np.testing.assert_allclose(ratio, 10 ** (-2 * 0.5 * img.ranges_m[on] / 10), rtol=0.2)
    speck = cfg.__class__(**{**cfg.__dict__, "speckle_looks": 1.0, "seed": 5})
    a, b = _floor_sonar(speck), _floor_sonar(speck)
    np.testing.assert_array_equal(a.intensity, b.intensity)
    assert not np.array_equal(a.intensity, a.clean)
    assert sonar.to_uint8(np.zeros((3, 3)), 40).max() == 0 and sonar.to_uint8(a.intensity, 40).max() == 255
    fan = sonar.fan_image(sonar.to_uint8(img.clean, 40), img, width_px=200)
    assert fan.shape[1] == 200 and fan.max() > 0


def test_view_matches_the_ground_truth_ray_caster(tiny_scene_path, tiny_mesh, tiny_cam_pose) -> None:
    from cadalign.sim.render import GroundTruthCaster
    from cadalign.sim.scene import build_scene
    from cadalign.sim.spec import load_scene

    scene = build_scene(load_scene(tiny_scene_path), tiny_scene_path, width=80, height=60)
    gt = GroundTruthCaster(scene).cast(tiny_cam_pose, with_full_masks=False)
    for engine in ("bvh", "torch"):
        v = views.render(tiny_mesh, scene.camera, tiny_cam_pose, engine_name=engine)
        assert (v.class_id == gt.class_id).mean() >= 0.999
        assert (v.part_id == gt.instance).mean() >= 0.999
        both = (v.depth_m > 0) & (gt.depth_m > 0)
        assert both.mean() > 0.5 and np.abs(v.depth_m[both] - gt.depth_m[both]).max() < 1e-4
    assert v.rgb[v.face < 0].max(initial=0) == 0


def test_return_strength_formula() -> None:
    cfg = sonar.SonarConfig(class_reflectivity=(0.5, 2.0), incidence_exponent=2.0, attenuation_db_per_m=0.1,
                            spreading_exponent=2.0)
    r = np.array([10.0, 10.0, 0.5, 10.0])
    cos = np.array([np.cos(np.radians(60)), -1.0, 1.0, 1.0])
    got = sonar.return_strength(cfg, r, cos, np.array([1, 0, 0, 7]))
    expected = np.array([2.0 * 0.25 * 10 ** -0.2 / 100, 0.5 * 10 ** -0.2 / 100, 0.5 * 10 ** -0.01, 10 ** -0.2 / 100])
    np.testing.assert_allclose(got, expected, rtol=1e-12)  # spreading is relative to 1 m; unknown class -> 1

"""End-to-end simulator tests on the tiny scene: BOP read-back, exact depth, determinism, resume, effects."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from cadalign.errors import ConfigError
from cadalign.formats.bop import BopScene
from cadalign.io import read_image, read_json
from cadalign.sim.run import SCENE_SUBDIR, simulate
from cadalign.testing.tiny_scene import ALL_EFFECTS, write_tiny_scene


def _ray_mask(mesh_m: trimesh.Trimesh, T_cam_from_obj: np.ndarray, K: np.ndarray, w: int, h: int) -> np.ndarray:
    """The object's silhouette sampled at pixel centres (i + 0.5) by a brute-force Moller-Trumbore test,
    an implementation independent of the Open3D ray caster under test."""
    posed = mesh_m.copy()
    posed.apply_transform(T_cam_from_obj)
    uv = posed.vertices @ K.T
    uv = uv[:, :2] / uv[:, 2:]
    u0, v0 = np.clip(np.floor(uv.min(0)).astype(int) - 1, 0, None)
    u1, v1 = np.minimum(np.ceil(uv.max(0)).astype(int) + 1, [w - 1, h - 1])
    vv, uu = np.mgrid[v0 : v1 + 1, u0 : u1 + 1]
    dirs = np.stack([(uu + 0.5 - K[0, 2]) / K[0, 0], (vv + 0.5 - K[1, 2]) / K[1, 1], np.ones(uu.shape)], -1)
    hit = _rays_hit(posed.vertices[posed.faces], dirs.reshape(-1, 3))
    mask = np.zeros((h, w), bool)
    mask[v0 : v1 + 1, u0 : u1 + 1] = hit.reshape(uu.shape)
    return mask


def _rays_hit(tri: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(R,) whether rays from the origin along ``dirs`` (R, 3) hit any triangle of ``tri`` (F, 3, 3)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    hit = np.zeros(len(dirs), bool)
    for s in range(0, len(dirs), 512):
        d = dirs[s : s + 512, None, :]
        p = np.cross(d, e2[None])
        det = np.einsum("fk,rfk->rf", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tvec = -tri[None, :, 0]
        u = np.einsum("rfk,rfk->rf", np.broadcast_to(tvec, p.shape), p) * inv
        q = np.cross(tvec, e1[None])
        v = np.einsum("rk,rfk->rf", d[:, 0], q) * inv
        t = np.einsum("fk,rfk->rf", e2, np.broadcast_to(q, p.shape)) * inv
        hit[s : s + 512] = (ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)).any(1)
    return hit


def test_layout_and_report(tiny_sim: Path) -> None:
    sdir = tiny_sim / SCENE_SUBDIR
    for name in ("scene_camera.json", "scene_gt.json", "scene_gt_info.json", "cameras.json", "objects.json"):
        assert (sdir / name).is_file(), name
    assert sorted(p.name for p in (tiny_sim / "frames").glob("*.png")) == [f"{k:06d}.png" for k in range(4)]
    assert (tiny_sim / "video.mp4").stat().st_size > 1000
    sheet = read_image(tiny_sim / "contact_sheet.png")
    assert sheet.shape[0] > 120 and sheet.shape[1] > 160 and sheet.std() > 5
    report = read_json(tiny_sim / "sim_report.json")
    assert set(report["seconds_per_frame_per_effect"]) == set(ALL_EFFECTS)
    info = read_json(tiny_sim / "gt" / "models" / "models_info.json")
    assert len(info) == 3 and all(v["diameter"] > 100 for v in info.values())  # mm
    # the calibration file a real camera would come with equals every frame's K
    from cadalign.sfm.report import intrinsics_from_cameras_json

    K = read_json(sdir / "scene_camera.json")["0"]["cam_K"]
    assert intrinsics_from_cameras_json(tiny_sim / "calibration.json") == (K[0], K[4], K[2], K[5])


def test_bop_masks_match_projected_cad(tiny_sim: Path) -> None:
    """Each unoccluded object's CAD, ray cast with its BOP pose, matches its mask_visib (IoU >= 0.98)."""
    scene = BopScene(tiny_sim / SCENE_SUBDIR)
    models = {}
    checked = 0
    for im_id in scene.ids:
        frame = scene.frame(im_id)
        for g, (inst, info) in enumerate(zip(frame.instances, frame.info, strict=True)):
            if info["visib_fract"] < 0.999 or info["px_count_all"] < 150:
                continue
            if inst.obj_id not in models:
                mesh = trimesh.load(tiny_sim / "gt" / "models" / f"obj_{inst.obj_id:06d}.ply", process=False)
                mesh.apply_scale(1e-3)  # BOP models are in mm
                models[inst.obj_id] = mesh
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = inst.T_cam_from_obj.R, inst.T_cam_from_obj.t
            proj = _ray_mask(models[inst.obj_id], T, frame.camera.K, frame.camera.width, frame.camera.height)
            visib = scene.mask(im_id, g, visible=True)
            iou = (proj & visib).sum() / max((proj | visib).sum(), 1)
            assert iou >= 0.98, (im_id, inst.obj_id, iou)
            checked += 1
    assert checked >= 3


def test_depth_back_projects_onto_the_meshes(tiny_sim: Path) -> None:
    """Back-projected BOP depth (mm PNG) lands on the posed CAD surfaces to within the 1 mm quantisation."""
    import open3d as o3d

    scene = BopScene(tiny_sim / SCENE_SUBDIR)
    objects = read_json(tiny_sim / SCENE_SUBDIR / "objects.json")["objects"]
    im_id = scene.ids[1]
    frame = scene.frame(im_id)
    depth = scene.depth_m(im_id)
    inst = read_image(tiny_sim / SCENE_SUBDIR / "instance" / f"{im_id:06d}.png", unchanged=True)
    rc = o3d.t.geometry.RaycastingScene()
    for g, bi in enumerate(frame.instances):
        mesh = trimesh.load(tiny_sim / "gt" / "models" / f"obj_{bi.obj_id:06d}.ply", process=False)
        v = np.asarray(mesh.vertices) * 1e-3 @ bi.T_cam_from_obj.R.T + bi.T_cam_from_obj.t
        rc.add_triangles(v.astype(np.float32), np.asarray(mesh.faces, dtype=np.uint32))
        assert objects[[o["obj_id"] for o in objects].index(bi.obj_id)]["obj_id"] == bi.obj_id
        sel = inst == g + 1
        assert sel.any()
    on_objects = (inst > 0) & (depth > 0)
    vv, uu = np.nonzero(on_objects)
    K = frame.camera.K
    z = depth[vv, uu]
    pts = np.stack([(uu + 0.5 - K[0, 2]) / K[0, 0] * z, (vv + 0.5 - K[1, 2]) / K[1, 1] * z, z], axis=1)
    dist = rc.compute_distance(o3d.core.Tensor(pts.astype(np.float32))).numpy()
    assert len(dist) > 200
    assert np.percentile(dist, 99) < 1.5e-3, np.percentile(dist, [50, 99, 100])


def test_scene_gt_poses_are_camera_from_object(tiny_sim: Path) -> None:
    """scene_gt = camera^-1 * object-in-world, with R orthonormal and t in mm."""
    sdir = tiny_sim / SCENE_SUBDIR
    cams = read_json(sdir / "cameras.json")["frames"]
    objects = {o["obj_id"]: o for o in read_json(sdir / "objects.json")["objects"]}
    gt = read_json(sdir / "scene_gt.json")
    for im_id, entries in gt.items():
        c = cams[f"{int(im_id):06d}.png"]
        T_cw = np.eye(4)
        T_cw[:3, :3], T_cw[:3, 3] = np.reshape(c["R_cam_from_world"], (3, 3)), c["t_cam_from_world_m"]
        for e in entries:
            o = objects[e["obj_id"]]
            T_wo = np.eye(4)
            T_wo[:3, :3], T_wo[:3, 3] = np.reshape(o["R_world_from_obj"], (3, 3)), o["t_world_from_obj_m"]
            T_co = T_cw @ T_wo
            np.testing.assert_allclose(np.reshape(e["cam_R_m2c"], (3, 3)), T_co[:3, :3], atol=1e-9)
            np.testing.assert_allclose(e["cam_t_m2c"], T_co[:3, 3] * 1000.0, atol=1e-6)


def test_effect_free_scene_is_the_clean_render(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With `effects = []` no effect is ever called and frames equal the bare render bit for bit."""
    from cadalign.sim import effects as fx
    from cadalign.sim.render import RGBRenderer
    from cadalign.sim.scene import build_scene
    from cadalign.sim.spec import load_scene
    from cadalign.sim.trajectory import pose_at

    def boom(*args: object, **kwargs: object) -> None:
        raise AssertionError("an undeclared effect was called")

    for name, spec in list(fx.EFFECTS.items()):
        monkeypatch.setitem(fx.EFFECTS, name, type(spec)(spec.params_type, boom, spec.uses_rng))
    scene_file = write_tiny_scene(tmp_path / "clean.toml", effects=[], frames=2)
    out = simulate(scene_file, tmp_path / "out", video=False, contact_sheet=False)
    report = read_json(out / "sim_report.json")
    assert report["seconds_per_frame_per_effect"] == {} and report["seconds_per_frame_effects_total"] == 0.0
    spec = load_scene(scene_file)
    renderer = RGBRenderer(build_scene(spec, scene_file))
    try:
        for k in range(2):
            clean = renderer.render(pose_at(spec.trajectory, k / spec.trajectory.fps, spec.seed))
            expected = (np.clip(clean, 0, 1) * 255 + 0.5).astype(np.uint8)
            np.testing.assert_array_equal(read_image(out / "frames" / f"{k:06d}.png"), expected)
    finally:
        renderer.close()


def test_deterministic_for_a_seed_and_resumes_after_interrupt(
    tmp_path: Path, tiny_scene_file: Path, tiny_sim: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An interrupted run, re-run, equals an uninterrupted one (same seed -> same bytes)."""
    import cadalign.sim.run as run_mod

    real_write = run_mod._write_frame
    calls = {"n": 0}

    def flaky_write(out_dir, scene, k, *args):  # noqa: ANN001, ANN202
        if calls["n"] == 2:
            raise KeyboardInterrupt
        calls["n"] += 1
        return real_write(out_dir, scene, k, *args)

    monkeypatch.setattr(run_mod, "_write_frame", flaky_write)
    out = tmp_path / "resumed"
    with pytest.raises(KeyboardInterrupt):
        simulate(tiny_scene_file, out, video=False, contact_sheet=False)
    assert not (out / "sim_report.json").exists()
    monkeypatch.setattr(run_mod, "_write_frame", real_write)
    simulate(tiny_scene_file, out, video=False, contact_sheet=False)
    assert read_json(out / "sim_report.json")["frames_rendered_this_run"] == 2
    for k in range(4):
        a = read_image(out / "frames" / f"{k:06d}.png")
        b = read_image(tiny_sim / "frames" / f"{k:06d}.png")
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(
            read_image(out / SCENE_SUBDIR / "depth" / f"{k:06d}.png", unchanged=True),
            read_image(tiny_sim / SCENE_SUBDIR / "depth" / f"{k:06d}.png", unchanged=True),
        )
    for name in ("scene_gt.json", "scene_camera.json", "scene_gt_info.json"):
        assert json.loads((out / SCENE_SUBDIR / name).read_text()) == json.loads(
            (tiny_sim / SCENE_SUBDIR / name).read_text()
        )


def test_other_seed_changes_the_noise_not_the_ground_truth(tmp_path: Path, tiny_scene_file: Path,
                                                           tiny_sim: Path) -> None:
    out = simulate(tiny_scene_file, tmp_path / "seed", seed=8, frames=1, video=False, contact_sheet=False)
    a = read_image(out / "frames" / "000000.png").astype(int)
    b = read_image(tiny_sim / "frames" / "000000.png").astype(int)
    assert np.abs(a - b).mean() > 0.2


def test_rerun_with_other_config_is_refused(tmp_path: Path, tiny_scene_file: Path) -> None:
    out = simulate(tiny_scene_file, tmp_path / "o", frames=1, video=False, contact_sheet=False)
    with pytest.raises(Exception, match="overwrite"):
        simulate(tiny_scene_file, out, frames=2, video=False, contact_sheet=False)


def test_unknown_effect_names_the_file_and_allowed_values(tmp_path: Path) -> None:
    from cadalign.sim.spec import load_scene

    bad = write_tiny_scene(tmp_path / "bad.toml", effects=["attenuation", "caustics"])
    with pytest.raises(ConfigError) as err:
        load_scene(bad)
    msg = str(err.value)
    assert "bad.toml" in msg and "caustics" in msg and "marine_snow" in msg


def test_misspelled_scene_key(tmp_path: Path) -> None:
    from cadalign.sim.spec import load_scene

    text = write_tiny_scene(tmp_path / "s.toml", effects=[]).read_text().replace("radius_m", "raduis_m")
    (tmp_path / "s.toml").write_text(text)
    with pytest.raises(ConfigError, match="raduis_m"):
        load_scene(tmp_path / "s.toml")


@pytest.mark.parametrize("scene", sorted((Path(__file__).parents[2] / "datasets" / "scenes").glob("*.toml")),
                         ids=lambda p: p.stem)
def test_shipped_scenes_validate(scene: Path, shared_data: Path) -> None:
    from cadalign.sim.scene import build_scene
    from cadalign.sim.spec import load_scene

    spec = load_scene(scene)
    built = build_scene(spec, scene)
    assert len(built.objects) == len(spec.objects)

"""GenLaM from a photograph (issue 47): tiny random checkpoints saved here load offline through the real code
paths; the camera from EXIF / --hfov / eq. (1); scale; photo -> mesh -> scan against the CAD scan; the CLI.

The tiny models are random: they test plumbing, not accuracy. Accuracy is checked with the oracle (exact
simulator depth as a point map)."""

from __future__ import annotations

import dataclasses
import json
import socket
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cadalign.emulate import lidar
from cadalign.emulate.layered_mesh import mesh_from_image
from cadalign.emulate.photo import PhotoConfig, depth_from_output, lift_photo
from cadalign.emulate.photo_camera import K_from_hfov, exif_focal_px, fit_point_map, parse_scale, scale_factor
from cadalign.emulate.photo_eval import compare_with_cad
from cadalign.emulate.pretrained import DepthOutput, load_depth_model, load_seg_model
from cadalign.emulate.run import SENSOR_FROM_CAM
from cadalign.emulate.views import render
from cadalign.errors import InputError
from cadalign.geometry import depth_to_points
from cadalign.types import Camera, Rigid3

transformers = pytest.importorskip("transformers")  # the `genlam` extra (in `dev`)
ADE_LIKE = {0: "wall", 1: "windowpane, window", 2: "floor", 3: "glass, drinking glass"}


def _tiny_dinov2():
    return transformers.Dinov2Config(hidden_size=32, num_hidden_layers=4, num_attention_heads=2,
                                     intermediate_size=64, patch_size=14, image_size=56,
                                     out_features=["stage1", "stage2", "stage3", "stage4"],
                                     reshape_hidden_states=False)


def _save_tiny(root: Path) -> dict[str, Path]:
    """Randomly initialised small checkpoints written by ``save_pretrained`` (seeded)."""
    import torch

    torch.manual_seed(0)
    paths = {}
    for kind in ("metric", "relative"):
        cfg = transformers.DepthAnythingConfig(
            backbone_config=_tiny_dinov2(), reassemble_hidden_size=32, neck_hidden_sizes=[8, 16, 32, 32],
            fusion_hidden_size=16, head_hidden_size=8, depth_estimation_type=kind, max_depth=20)
        paths[f"da_{kind}"] = root / f"da_{kind}"
        transformers.DepthAnythingForDepthEstimation(cfg).save_pretrained(paths[f"da_{kind}"])
    (paths["da_metric"] / "preprocessor_config.json").write_text(json.dumps(
        {"image_mean": [0.5, 0.5, 0.5], "image_std": [0.5, 0.5, 0.5]}))
    dpt = transformers.DPTConfig(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, intermediate_size=64,
                                 image_size=32, patch_size=8, neck_hidden_sizes=[8, 16, 32, 32],
                                 fusion_hidden_size=16, backbone_out_indices=[0, 1, 2, 3])
    paths["dpt"] = root / "dpt"
    transformers.DPTForDepthEstimation(dpt).save_pretrained(paths["dpt"])
    seg = transformers.SegformerConfig(
        num_encoder_blocks=2, depths=[1, 1], sr_ratios=[2, 1], hidden_sizes=[8, 16], patch_sizes=[7, 3],
        strides=[4, 2], num_attention_heads=[1, 1], mlp_ratios=[2, 2], decoder_hidden_size=16, num_labels=4,
        id2label=ADE_LIKE, label2id={v: k for k, v in ADE_LIKE.items()})
    paths["seg"] = root / "seg"
    transformers.SegformerForSemanticSegmentation(seg).save_pretrained(paths["seg"])
    paths["vit"] = root / "vit"
    transformers.ViTModel(transformers.ViTConfig(hidden_size=16, num_hidden_layers=1, num_attention_heads=1,
                                                 intermediate_size=16, image_size=16, patch_size=8)
                          ).save_pretrained(paths["vit"])
    return paths


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return _save_tiny(tmp_path_factory.mktemp("ckpt"))


@pytest.fixture
def offline(monkeypatch: pytest.MonkeyPatch) -> list:
    """No network: HF offline mode, and any socket connection attempt is recorded and refused."""
    attempts: list = []

    def refuse(self, address):  # noqa: ANN001
        attempts.append(address)
        raise OSError(f"network access attempted: {address}")

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(socket.socket, "connect", refuse)
    monkeypatch.setattr(socket.socket, "connect_ex", refuse)
    return attempts


@pytest.fixture(scope="module")
def sim_frame(tiny_mesh, tiny_cam_pose):
    """The simulator's exact frame of the tiny CAD scene: rgb, depth, class, camera, pose (160 x 120, 60 deg)."""
    cam = Camera(K_from_hfov(160, 120, 60.0), 160, 120)
    v = render(tiny_mesh, cam, tiny_cam_pose)
    return v, cam


def _photo(tmp_path: Path, rgb: np.ndarray, name: str = "photo.png") -> Path:
    from cadalign.io import write_image

    return write_image(tmp_path / name, rgb)


class TestPretrained:
    def test_all_architectures_load_offline_and_predict_at_photo_size(self, ckpts, offline) -> None:
        rgb = np.random.default_rng(0).integers(0, 256, (30, 41, 3), dtype=np.uint8)
        for name, kind in (("da_metric", "metric"), ("da_relative", "disparity"), ("dpt", "disparity")):
            out = load_depth_model(ckpts[name])(rgb)
            assert out.kind == kind and out.value.shape == (30, 41) and np.all(np.isfinite(out.value))
        seg = load_seg_model(ckpts["seg"])
        prob = seg.predict(rgb)
        assert prob.shape == (4, 30, 41)
        np.testing.assert_allclose(prob.sum(0), 1.0, atol=1e-5)
        assert seg.class_names == tuple(ADE_LIKE.values()) and seg.pane_classes() == (1, 3)
        assert offline == []  # nothing even tried

    def test_the_offline_guard_catches_a_connection(self, offline) -> None:
        with pytest.raises(OSError, match="network access attempted"):
            socket.create_connection(("127.0.0.1", 9))
        assert offline

    def test_missing_unsupported_and_broken_checkpoints(self, ckpts, tmp_path, offline) -> None:
        with pytest.raises(InputError, match="no config.json.*depth_anything, dpt"):
            load_depth_model(tmp_path / "nowhere")
        with pytest.raises(InputError, match="'vit'; supported architectures: depth_anything, dpt"):
            load_depth_model(ckpts["vit"])
        with pytest.raises(InputError, match="'segformer'; supported architectures: depth_anything, dpt"):
            load_depth_model(ckpts["seg"])
        with pytest.raises(InputError, match="supported architectures: segformer"):
            load_seg_model(ckpts["dpt"])
        broken = tmp_path / "broken"
        broken.mkdir()
        (broken / "config.json").write_text((ckpts["dpt"] / "config.json").read_text())  # no weights
        with pytest.raises(InputError, match="could not load"):
            load_depth_model(broken)
        assert offline == []


class TestCamera:
    def test_exif_35mm_focal_length(self, tmp_path) -> None:
        from PIL import Image

        im = Image.fromarray(np.zeros((30, 40, 3), np.uint8))
        exif = im.getexif()
        exif.get_ifd(0x8769)[0xA405] = 24  # 24 mm equivalent
        im.save(tmp_path / "a.jpg", exif=exif)
        assert exif_focal_px(tmp_path / "a.jpg", 40, 30) == pytest.approx(24 * 40 / 36)
        im.save(tmp_path / "b.png")
        assert exif_focal_px(tmp_path / "b.png", 40, 30) is None

    @pytest.mark.parametrize("shift", [0.0, 0.8, -0.5])
    def test_eq1_recovers_the_focal_length_from_exact_point_maps(self, sim_frame, shift) -> None:
        v, cam = sim_frame
        P, _ = depth_to_points(cam.K, v.depth_m)
        P[..., 2] -= shift  # a point map known up to a z-shift
        f, dz, res = fit_point_map(P)
        assert abs(f / cam.fx - 1) < 0.005 and dz == pytest.approx(shift, abs=1e-6) and res < 1e-6

    def test_eq1_with_two_percent_depth_noise_stays_within_three_percent(self, sim_frame) -> None:
        v, cam = sim_frame
        P, _ = depth_to_points(cam.K, v.depth_m)
        rng = np.random.default_rng(0)
        P = P + 0.02 * P[..., 2:] * rng.standard_normal(P.shape)  # 2 % of the depth on each coordinate
        P[..., 2] -= 0.8
        f, _, res = fit_point_map(P)
        assert abs(f / cam.fx - 1) < 0.03 and res > 0.1

    def test_a_flat_point_map_is_refused_with_the_fix(self) -> None:
        P, _ = depth_to_points(K_from_hfov(40, 30, 60), np.full((30, 40), 2.0))
        with pytest.raises(InputError, match="--hfov or --calib"):
            fit_point_map(P)

    def test_scale_forms_and_errors(self, tmp_path) -> None:
        depth = np.array([[1.0, 2.0], [3.0, 0.0]])
        assert scale_factor(depth, parse_scale("distance:4")) == pytest.approx(2.0)
        assert scale_factor(depth, parse_scale("pixel:1,0:5")) == pytest.approx(2.5)
        np.savez(tmp_path / "s.npz", depth_m=np.array([[0.0, 6.0], [0.0, 0.0]]))
        assert scale_factor(depth, parse_scale(f"depth:{tmp_path / 's.npz'}")) == pytest.approx(3.0)
        for bad in ("distance:-1", "pixel:1:3", "cad", "distance:x"):
            with pytest.raises(InputError, match="--scale-from"):
                parse_scale(bad)
        with pytest.raises(InputError, match="without predicted depth"):
            scale_factor(depth, parse_scale("pixel:1,1:5"))

    def test_disparity_becomes_depth_and_nonpositive_is_no_depth(self) -> None:
        d = depth_from_output(DepthOutput(np.array([[2.0, 0.5], [0.0, -1.0]]), "disparity"))
        np.testing.assert_allclose(d, [[0.5, 2.0], [0.0, 0.0]])


def _oracle_npz(tmp_path: Path, v, shift: float = 0.7) -> Path:
    P, _ = depth_to_points(K_from_hfov(v.rgb.shape[1], v.rgb.shape[0], 60.0), v.depth_m)
    P[..., 2] -= shift
    np.savez(tmp_path / "pm.npz", rgb=v.rgb, points=P)
    return tmp_path / "pm.npz"


def test_photo_mesh_scan_matches_the_cad_scan_from_the_same_pose(sim_frame, tiny_mesh, tiny_cam_pose,
                                                                 tmp_path) -> None:
    """Oracle depth (exact point map up to a shift) and oracle classes: eq. (1) camera -> mesh -> LiDAR scan
    agrees with the CAD scan on every ray that hits a surface seen in the photo."""
    v, cam = sim_frame
    res = lift_photo(_oracle_npz(tmp_path, v), PhotoConfig())
    assert res.info["camera"] == "point_map" and abs(res.image.K[0, 0] / cam.fx - 1) < 1e-6
    inp = dataclasses.replace(res.image, class_id=v.class_id, T_world_from_cam=tiny_cam_pose.matrix())
    mesh = mesh_from_image(inp, PhotoConfig().mesh)
    cfg = lidar.LidarConfig(channels=64, vfov_deg=(-30, 30), horizontal_res_deg=0.5, range_noise_m=0.0)
    T_lidar = Rigid3(tiny_cam_pose.R @ SENSOR_FROM_CAM.T, tiny_cam_pose.t)
    agree = compare_with_cad(mesh, tiny_mesh, T_lidar, cfg, cam, tiny_cam_pose, v.depth_m)
    assert agree.n_seen > 1000 and agree.coverage > 0.95  # misses: the half-pixel rim, triangles cut at jumps
    assert agree.range_err_median_m < 0.005 and agree.class_agreement > 0.97
    moved = Rigid3(T_lidar.R, T_lidar.t + tiny_cam_pose.R @ [0.3, 0.0, 0.0])  # 30 cm to the camera's right
    agree2 = compare_with_cad(mesh, tiny_mesh, moved, cfg, cam, tiny_cam_pose, v.depth_m)
    assert agree2.n_seen > 1000 and agree2.range_err_median_m < 0.01 and agree2.class_agreement > 0.95


class TestCli:
    def test_photo_end_to_end_with_tiny_models_then_lidar_of_the_mesh(self, ckpts, sim_frame, tmp_path,
                                                                      offline) -> None:
        from cadalign.cli.main import app

        v, _ = sim_frame
        photo = _photo(tmp_path, v.rgb)
        out = tmp_path / "out"
        args = ["emulate", "mesh", str(photo), "--depth-model", str(ckpts["da_relative"]), "--seg-model",
                str(ckpts["seg"]), "--hfov", "60", "--scale-from", "distance:3", "--out", str(out)]
        r = CliRunner().invoke(app, args)
        assert r.exit_code == 0, r.output
        for f in ("layered_mesh.ply", "scan.npz", "scan.ply", "contact.png", "photo_input.npz", "lidar_pose.json"):
            assert (out / f).is_file(), f
        info = json.loads((out / "photo.json").read_text())
        assert info["metric"] and info["camera"] == "hfov" and info["hfov_deg"] == pytest.approx(60)
        assert info["pane_pixels"] > 0  # from the classes named 'windowpane, window' / 'glass'
        z = np.load(out / "photo_input.npz")
        assert np.median(z["depth_m"][z["depth_m"] > 0]) == pytest.approx(3.0)
        assert tuple(z["class_names"]) == tuple(ADE_LIKE.values())
        assert all(k in info for k in ("depth_s", "classes_s", "mesh_s", "scan_s"))
        scan = np.load(out / "scan.npz")
        assert len(scan["range_m"]) > 0 and scan["class_id"].max() <= 3 and "pane_id" in scan.files
        r = CliRunner().invoke(app, ["emulate", "mesh", str(photo), "--depth-model", str(ckpts["da_relative"]),
                                     "--hfov", "60", "--scale-from", "distance:3", "--out", str(out)])
        assert r.exit_code != 0 and "overwrite" in r.output  # another config in the same folder is refused
        r = CliRunner().invoke(app, ["emulate", "lidar", str(out / "layered_mesh.ply"), "--pose",
                                     str(out / "lidar_pose.json"), "--preset", "vlp16", "--out", str(tmp_path / "l")])
        assert r.exit_code == 0, r.output
        assert (tmp_path / "l" / "scan.ply").is_file()
        assert offline == []

    def test_point_map_with_a_pane_mask_gives_a_pane_in_the_scan(self, sim_frame, tmp_path) -> None:
        from cadalign.cli.main import app
        from cadalign.io import write_image

        v, _ = sim_frame
        mask = np.zeros(v.depth_m.shape, np.uint8)
        cls = v.class_id[v.depth_m > 0]
        largest = np.bincount(cls).argmax()
        mask[(v.class_id == largest) & (v.depth_m > 0)] = 255
        write_image(tmp_path / "mask.png", mask)
        r = CliRunner().invoke(app, ["emulate", "mesh", str(_oracle_npz(tmp_path, v)), "--pane-mask",
                                     str(tmp_path / "mask.png"), "--out", str(tmp_path / "o")])
        assert r.exit_code == 0, r.output
        info = json.loads((tmp_path / "o" / "photo.json").read_text())
        assert info["camera"] == "point_map" and info["eq1_residual_px"] < 1e-6
        assert info["panes"] >= 1 and info["scan_pane_returns"] > 0
        r = CliRunner().invoke(app, ["emulate", "view", str(tmp_path / "o" / "layered_mesh.ply"), "--pose", "0,0,0",
                                     "--preset", "small", "--out", str(tmp_path / "v")])
        assert r.exit_code == 0, r.output
        seen = np.load(tmp_path / "v" / "view.npz")["face"] >= 0  # the photo's camera (60 deg) inside the 70 deg view
        assert seen.mean() > 0.3 and seen[60, 80]

    def test_relative_depth_without_scale_says_no_metric_scale(self, ckpts, tmp_path) -> None:
        from cadalign.cli.main import app

        photo = _photo(tmp_path, np.random.default_rng(1).integers(0, 256, (24, 32, 3), dtype=np.uint8))
        r = CliRunner().invoke(app, ["emulate", "mesh", str(photo), "--depth-model", str(ckpts["da_relative"]),
                                     "--out", str(tmp_path / "o")])
        assert r.exit_code == 0, r.output
        info = json.loads((tmp_path / "o" / "photo.json").read_text())
        assert info["metric"] is False and info["camera"] == "default"

    def test_readable_errors(self, ckpts, tmp_path) -> None:
        from cadalign.cli.main import app

        photo = _photo(tmp_path, np.zeros((24, 32, 3), np.uint8))
        r = CliRunner().invoke(app, ["emulate", "mesh", str(photo), "--out", str(tmp_path / "a")])
        assert r.exit_code != 0 and "--depth-model" in r.output
        r = CliRunner().invoke(app, ["emulate", "mesh", str(photo), "--depth-model", str(ckpts["vit"]),
                                     "--out", str(tmp_path / "b")])
        assert r.exit_code != 0 and "depth_anything, dpt" in r.output


class TestScaleFromReference:
    def test_fit_disparity_recovers_scale_and_shift(self) -> None:
        from cadalign.emulate.photo_camera import fit_disparity

        ref = np.random.default_rng(0).uniform(1, 10, (20, 30))
        sparse = np.where(np.random.default_rng(1).random(ref.shape) < 0.05, ref, 0.0)
        a, b = fit_disparity((1 / ref - 0.1) / 3.0, sparse)
        assert (a, b) == pytest.approx((3.0, 0.1), rel=1e-9)
        with pytest.raises(InputError, match="too few distinct"):
            fit_disparity(np.ones((4, 4)), np.full((4, 4), 2.0))

    def test_relative_disparity_scaled_by_the_cad_from_a_known_pose(self, sim_frame, tiny_scene_path,
                                                                    tiny_cam_pose, tmp_path) -> None:
        from cadalign.emulate.photo_camera import ScaleFrom
        from cadalign.io import write_json

        v, cam = sim_frame
        seen = v.depth_m > 0
        disparity = np.where(seen, (1 / np.where(seen, v.depth_m, 1.0) - 0.05) / 7.0, 0.0)  # affine, unknown
        pose = write_json(tmp_path / "pose.json", {"T_world_from_cam": tiny_cam_pose.matrix().tolist()})
        res = lift_photo(_photo(tmp_path, v.rgb), PhotoConfig(),
                         depth_fn=lambda rgb: DepthOutput(disparity, "disparity"), hfov_deg=60.0,
                         scale_from=ScaleFrom("cad", path=tiny_scene_path, pose=str(pose)))
        assert res.info["metric"] and res.info["scale"] == pytest.approx([7.0, 0.05], rel=1e-4)
        np.testing.assert_allclose(res.image.depth_m[seen], v.depth_m[seen], rtol=1e-4)
        assert parse_scale(f"cad:{tiny_scene_path}:{pose}").pose == str(pose)


def test_bench_photo_on_the_tiny_scene(tiny_scene_path, tmp_path) -> None:
    from cadalign.bench.photo import bench_photo

    out = bench_photo(tiny_scene_path, tmp_path, frames=1, width=96, height=72)
    (row,) = out["frames"]
    assert row["focal_err_exact"] < 1e-6 and row["focal_err_noisy"] < 0.03
    assert row["same_pose"]["class_agreement"] > 0.95 and (tmp_path / "bench_photo.json").is_file()


class TestSuperResolution:
    @pytest.mark.parametrize(("scale", "shape_out"), [(4, (20, 28, 3)), (2, (10, 14, 3)), (1, (5, 7, 3))])
    def test_a_saved_rrdbnet_loads_and_upscales(self, tmp_path, scale, shape_out) -> None:
        import torch

        from cadalign.emulate.superres import RRDBNet, load_sr_model

        torch.manual_seed(0)
        torch.save({"params_ema": RRDBNet(scale, feat=8, blocks=2, grow=4).state_dict()}, tmp_path / "sr.pth")
        up = load_sr_model(tmp_path / "sr.pth")(np.full((5, 7, 3), 128, np.uint8))
        assert up.shape == shape_out and up.dtype == np.uint8

    def test_foreign_or_missing_weights_are_refused(self, tmp_path) -> None:
        import torch

        from cadalign.emulate.superres import load_sr_model

        torch.save({"params": {"conv.weight": torch.zeros(3, 3, 3, 3)}}, tmp_path / "x.pth")
        with pytest.raises(InputError, match="only RRDBNet"):
            load_sr_model(tmp_path / "x.pth")
        with pytest.raises(InputError, match="not found"):
            load_sr_model(tmp_path / "none.pth")

    def test_photo_depth_on_the_upscaled_frame_comes_back_at_the_photo_size(self, ckpts, sim_frame,
                                                                             tmp_path) -> None:
        import torch

        from cadalign.cli.main import app
        from cadalign.emulate.superres import RRDBNet

        torch.manual_seed(0)
        torch.save(RRDBNet(4, feat=8, blocks=1, grow=4).state_dict(), tmp_path / "sr.pth")
        v, _ = sim_frame
        r = CliRunner().invoke(app, ["emulate", "mesh", str(_photo(tmp_path, v.rgb[:48, :64])), "--depth-model",
                                     str(ckpts["da_metric"]), "--sr-model", str(tmp_path / "sr.pth"), "--hfov", "60",
                                     "--out", str(tmp_path / "o")])
        assert r.exit_code == 0, r.output
        info = json.loads((tmp_path / "o" / "photo.json").read_text())
        assert info["sr_scale"] == 4 and np.load(tmp_path / "o" / "photo_input.npz")["depth_m"].shape == (48, 64)


def test_depth_plus_rays_npz_and_calib_and_reuse(sim_frame, tmp_path) -> None:
    from cadalign.cli.main import app
    from cadalign.geometry import pixel_rays
    from cadalign.io import write_json

    v, cam = sim_frame
    rays = pixel_rays(cam.K, cam.width, cam.height, normalize=True)  # unit rays: the fit rescales them to z = 1
    np.savez(tmp_path / "dr.npz", rgb=v.rgb, depth_m=v.depth_m, rays=rays)
    res = lift_photo(tmp_path / "dr.npz", PhotoConfig())
    assert res.info["camera"] == "point_map" and res.image.K[0, 0] == pytest.approx(cam.fx, rel=1e-9)
    np.testing.assert_allclose(res.image.depth_m, v.depth_m, atol=1e-9)
    K2 = cam.K.copy()
    K2[0, 0] = K2[1, 1] = 123.0
    write_json(tmp_path / "cameras.json", {"K": K2.ravel().tolist(), "width": 2 * cam.width, "height": 2 * cam.height})
    args = ["emulate", "mesh", str(tmp_path / "dr.npz"), "--calib", str(tmp_path / "cameras.json"), "--out",
            str(tmp_path / "o")]
    assert CliRunner().invoke(app, args).exit_code == 0
    info = json.loads((tmp_path / "o" / "photo.json").read_text())
    assert info["camera"] == "calib" and info["K"][0][0] == 61.5  # wins over eq. (1); for a 2x larger image
    stamp = (tmp_path / "o" / "layered_mesh.ply").stat().st_mtime_ns
    r = CliRunner().invoke(app, args)  # same config: finished work is reused, nothing rewritten
    assert r.exit_code == 0 and (tmp_path / "o" / "layered_mesh.ply").stat().st_mtime_ns == stamp

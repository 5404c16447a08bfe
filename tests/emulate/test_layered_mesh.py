"""Layered mesh from one image: triangle cuts, layers, round trip through a novel view, panes, PLY I/O."""

from __future__ import annotations

import numpy as np
import pytest

from cadalign.emulate.layered_mesh import LayeredMeshConfig, grid_faces, mesh_from_image
from cadalign.emulate.sources import ImageInput, ply_mesh, write_ply
from cadalign.emulate.views import render
from cadalign.errors import InputError
from cadalign.geometry import intrinsics
from cadalign.types import Camera, Rigid3

H, W = 24, 32
K = intrinsics(30.0, 30.0, 16.0, 12.0)


def _image(depth: np.ndarray, **kw) -> ImageInput:
    rng = np.random.default_rng(0)
    return ImageInput(rng.integers(0, 256, depth.shape + (3,), dtype=np.uint8), depth, K, **kw)


def test_grid_faces_count_and_cuts() -> None:
    flat = np.full((H, W), 2.0)
    ok = np.ones((H, W), bool)
    assert len(grid_faces(flat, ok, 0.05)) == 2 * (H - 1) * (W - 1)
    hole = ok.copy()
    hole[10, 10] = False  # an interior vertex belongs to 6 triangles of this split
    assert len(grid_faces(flat, hole, 0.05)) == 2 * (H - 1) * (W - 1) - 6
    step = flat.copy()
    step[:, 16:] = 2.2  # a 10 % jump between columns 15 and 16: the quads across it are cut (both triangles)
    assert len(grid_faces(step, ok, 0.05)) == 2 * (H - 1) * (W - 2)
    assert len(grid_faces(step, ok, 0.15)) == 2 * (H - 1) * (W - 1)  # below the threshold: kept


def test_layers_and_camera_facing_normals() -> None:
    depth = np.full((H, W), 3.0)
    cls = np.zeros((H, W), np.int32)
    cls[:, W // 2:] = 2
    mesh = mesh_from_image(_image(depth, class_id=cls, part_id=cls * 5), LayeredMeshConfig())
    assert mesh.n_faces == 2 * (H - 1) * (W - 1)
    assert set(np.unique(mesh.class_id)) == {0, 2} and set(np.unique(mesh.part_id)) == {0, 10}
    assert np.all(mesh.pane_id == 0)
    np.testing.assert_allclose(mesh.face_normals() @ [0, 0, -1.0], 1.0, atol=1e-12)


def test_novel_view_from_the_source_camera_reproduces_the_image() -> None:
    yy, xx = np.mgrid[0:H, 0:W]
    depth = 2.0 + 0.01 * xx + 0.02 * yy  # a smooth slanted surface
    depth[5:9, 20:26] = 1.0  # a box in front: cut from the background by the jump
    inp = _image(depth)
    mesh = mesh_from_image(inp, LayeredMeshConfig())
    v = render(mesh, Camera(K, W, H), Rigid3())
    hit = v.face >= 0
    assert hit[1:-1, 1:-1].mean() > 0.9
    np.testing.assert_allclose(v.depth_m[hit], depth[hit], atol=1e-5)  # every seen pixel centre is a vertex
    np.testing.assert_array_equal(v.rgb[hit], inp.rgb[hit])  # vertex colours at barycentric corners
    assert not hit[5:9, 19].any() or np.all(np.abs(v.depth_m[5:9, 19] - depth[5:9, 19]) < 1e-5)


def test_world_pose_stride_and_invalid_inputs() -> None:
    T = Rigid3(np.eye(3), [1.0, 2.0, 3.0])
    depth = np.full((H, W), 2.0)
    depth[0, 0] = np.nan
    depth[1, 1] = 0.0
    mesh = mesh_from_image(_image(depth, T_world_from_cam=T.matrix()), LayeredMeshConfig(stride=2))
    assert np.allclose(mesh.vertices_m[:, 2], 5.0)
    assert mesh.n_faces == 2 * (H // 2 - 1) * (W // 2 - 1) - 1  # pixel (0, 0) is a corner: 1 triangle lost
    with pytest.raises(InputError, match="class_id"):
        mesh_from_image(_image(depth, class_id=np.zeros((2, 2))), LayeredMeshConfig())
    with pytest.raises(InputError, match="no triangle survives"):
        mesh_from_image(_image(np.zeros((H, W))), LayeredMeshConfig())
    with pytest.raises(InputError, match=r"\(H, W, 3\)"):
        mesh_from_image(ImageInput(np.zeros((H, W)), depth, K), LayeredMeshConfig())


def test_pane_replaces_the_unreliable_depth_inside_a_window() -> None:
    depth = np.full((H, W), 4.0)
    window = np.zeros((H, W), bool)
    window[6:18, 8:24] = True
    depth[7:17, 9:23] = 9.0  # the depth sees through the glass, except on the rim
    cls = np.where(window, 3, 1)
    mesh = mesh_from_image(_image(depth, class_id=cls, pane_mask=window), LayeredMeshConfig())
    assert mesh.pane_id.max() == 1
    pane = mesh.pane_id == 1
    assert np.all(mesh.class_id[pane] == 3)
    v = render(mesh, Camera(K, W, H), Rigid3())
    inside = np.zeros((H, W), bool)
    inside[8:16, 10:22] = True
    np.testing.assert_allclose(v.depth_m[inside], 4.0, atol=1e-5)  # the pane, not the see-through depth
    assert np.all(v.pane_id[inside] == 1) and np.all(v.class_id[inside] == 3)
    assert np.all(v.pane_id[0] == 0)
    without = mesh_from_image(_image(depth, pane_mask=window), LayeredMeshConfig(panes=False))
    assert without.pane_id.max() == 0


def test_ply_round_trip_keeps_every_layer(tmp_path) -> None:
    depth = np.full((H, W), 2.0)
    mesh = mesh_from_image(_image(depth, class_id=np.ones((H, W)), part_id=np.full((H, W), 7)), LayeredMeshConfig())
    back = ply_mesh(write_ply(mesh, tmp_path / "m.ply"))
    np.testing.assert_array_equal(back.vertices_m, mesh.vertices_m)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    for name in ("face_rgb", "class_id", "part_id", "pane_id", "vertex_rgb"):
        np.testing.assert_array_equal(getattr(back, name), getattr(mesh, name))
    with pytest.raises(InputError, match="not found"):
        ply_mesh(tmp_path / "missing.ply")


def test_predictions_for_a_scene_or_mesh_source_are_refused(tmp_path) -> None:
    """A scene or mesh has exact depth and classes; predictors handed with one would never be called."""
    from cadalign.emulate.sources import load_source

    mesh = mesh_from_image(_image(np.full((H, W), 2.0)), LayeredMeshConfig())
    ply = write_ply(mesh, tmp_path / "map.ply")
    with pytest.raises(InputError, match=r"map\.ply: depth_fn replace.*Drop the option"):
        load_source(ply, depth_fn=lambda rgb, cam: np.ones(rgb.shape[:2]))
    with pytest.raises(InputError, match=r"scene\.toml: depth_fn and seg_fn replace"):
        load_source(tmp_path / "scene.toml", depth_fn=lambda rgb, cam: None, seg_fn=lambda rgb: None)
    assert len(load_source(ply).faces) == len(mesh.faces)  # without predictors the mesh loads


def test_predicted_depth_and_classes_replace_the_ground_truth() -> None:
    from cadalign.emulate.sources import with_predictions

    inp = _image(np.full((H, W), 2.0), class_id=np.zeros((H, W), np.int32))
    seen = {}

    def depth_fn(rgb, camera):
        seen["camera"] = camera
        return np.full(rgb.shape[:2], 3.0)

    def seg_fn(rgb):
        p = np.zeros((3,) + rgb.shape[:2])
        p[2, :, : W // 2] = 1.0
        p[1, :, W // 2:] = 1.0
        return p

    out = with_predictions(inp, depth_fn, seg_fn)
    assert seen["camera"].width == W and np.array_equal(seen["camera"].K, K)
    mesh = mesh_from_image(out, LayeredMeshConfig())
    assert np.allclose(mesh.vertices_m[:, 2], 3.0) and set(np.unique(mesh.class_id)) == {1, 2}
    same = with_predictions(inp)  # nothing to replace
    assert same.depth_m is inp.depth_m and same.class_id is inp.class_id
    with pytest.raises(InputError, match="segmentation predictor returned"):
        with_predictions(inp, seg_fn=lambda rgb: np.zeros((H, W)))


def test_fused_map_ply_with_vertex_colour_and_class(tmp_path) -> None:
    """The layout of cadalign.fuse's mesh.ply: per-vertex colour and ushort class, no face properties."""
    v = np.zeros(4, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1"), ("green", "u1"),
                           ("blue", "u1"), ("class", "<u2"), ("confidence", "<f4")])
    v["x"], v["y"], v["z"] = [0, 1, 1, 0], [0, 0, 1, 1], 2.0
    v["red"], v["class"] = [0, 100, 200, 50], [2, 2, 1, 1]
    f = np.zeros(2, dtype=[("n", "u1"), ("v", "<i4", (3,))])
    f["n"], f["v"] = 3, [[0, 1, 2], [0, 2, 3]]
    props = "".join(f"property {t} {n}\n" for n, t in (("x", "double"), ("y", "double"), ("z", "double"),
                    ("red", "uchar"), ("green", "uchar"), ("blue", "uchar"), ("class", "ushort"),
                    ("confidence", "float")))
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex 4\n{props}element face 2\n"
              "property list uchar int vertex_indices\nend_header\n")
    (tmp_path / "map.ply").write_bytes(header.encode() + v.tobytes() + f.tobytes())
    mesh = ply_mesh(tmp_path / "map.ply")
    assert mesh.class_id.tolist() == [2, 1]  # majority of each face's corners
    np.testing.assert_array_equal(mesh.vertex_rgb[:, 0], [0, 100, 200, 50])
    view = render(mesh, Camera(K, W, H), Rigid3(np.eye(3), [0.5, 0.5, 0.0]))
    # pixel (12, 20) sees (0.8, 0.5333) on face 0 = (1 - u - v) V0 + u V1 + v V2 with u = 0.2667, v = 0.5333
    assert view.rgb[12, 20, 0] == round(0.8 * 100 - 0.5333 * 100 + 0.5333 * 200 - 0.0001)
    assert view.class_id[12, 20] == 2 and view.class_id[16, 12] == 1

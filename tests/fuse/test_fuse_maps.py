"""TSDF and surfel maps on the tiny simulated scene: geometry lands on the truth, labels are right, maps
re-open and extend, bad inputs fail clearly, far-from-origin worlds keep their precision."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cadalign.errors import InputError
from cadalign.fuse.base import FuseFrame
from cadalign.fuse.config import FuseConfig
from cadalign.fuse.inputs import FrameSource, open_source
from cadalign.fuse.map_io import load_map, new_map, save_map
from cadalign.metrics.map import point_truth_labels
from cadalign.types import Rigid3

METHODS = ["tsdf", "surfel"]


def _cfg(small_cfg: FuseConfig, method: str) -> FuseConfig:
    return dataclasses.replace(small_cfg, method=method, surfel_min_confidence=0.5)


def _fused(src: FrameSource, cfg: FuseConfig, ids: list[int] | None = None):  # -> SemanticMap
    m = new_map(cfg, src.n_classes)
    for i in ids if ids is not None else src.ids:
        m.integrate(src.frame(i))
    return m


def _truth_points(src: FrameSource, stride: int = 3) -> np.ndarray:
    """World points back-projected from the exact depth of every frame (every ``stride``-th pixel)."""
    out = []
    for i in src.ids:
        f = src.frame(i)
        v, u = np.nonzero(f.depth_m > 0)
        v, u = v[::stride], u[::stride]
        z = f.depth_m[v, u].astype(np.float64)
        cam = f.camera
        pc = np.stack([(u + 0.5 - cam.cx) / cam.fx * z, (v + 0.5 - cam.cy) / cam.fy * z, z], 1)
        out.append(f.T_cam_from_world.inverse().apply(pc))
    return np.concatenate(out)


@pytest.fixture(scope="module")
def src(fuse_sim: Path) -> FrameSource:
    return open_source(fuse_sim)


@pytest.fixture(scope="module", params=METHODS)
def fused(request: pytest.FixtureRequest, src: FrameSource, small_cfg: FuseConfig):  # -> (method, map)
    return request.param, _fused(src, _cfg(small_cfg, request.param))


def _projective_residual(points: np.ndarray, src: FrameSource) -> np.ndarray:
    """Per point, the smallest |z - true depth| over the frames it projects into (inf if none)."""
    best = np.full(len(points), np.inf)
    for i in src.ids:
        f = src.frame(i)
        pc = f.T_cam_from_world.apply(points)
        z = np.maximum(pc[:, 2], 1e-6)
        u = np.floor(pc[:, 0] / z * f.camera.fx + f.camera.cx).astype(int)
        v = np.floor(pc[:, 1] / z * f.camera.fy + f.camera.cy).astype(int)
        ok = (pc[:, 2] > 0) & (u >= 0) & (u < f.camera.width) & (v >= 0) & (v < f.camera.height)
        d = np.zeros(len(points))
        d[ok] = f.depth_m[v[ok], u[ok]]
        ok &= d > 0
        best[ok] = np.minimum(best[ok], np.abs(d[ok] - pc[ok, 2]))
    return best


def test_fused_gt_depth_lies_within_a_voxel_of_the_mesh(fused, src: FrameSource, small_cfg: FuseConfig) -> None:
    from cadalign.metrics.map import _distance_to_mesh

    method, m = fused
    mesh = m.extract_mesh()
    voxel = small_cfg.voxel_m
    # truth -> map: points of the exact depth maps lie on the fused surface
    d = _distance_to_mesh(_truth_points(src), [(mesh.points_m, mesh.faces)])[0]
    assert np.median(d) < 0.5 * voxel, method
    assert np.mean(d < voxel) > 0.9, method
    # map -> truth: the fused surface agrees with the depth the frames measured
    r = _projective_residual(m.extract_points().points_m, src)
    assert np.median(r) < 0.5 * voxel and np.mean(r < voxel) > 0.75, method


def test_fused_labels_match_the_class_maps(fused, src: FrameSource, small_cfg: FuseConfig) -> None:
    method, m = fused
    geom = m.extract_mesh() if method == "tsdf" else m.extract_points()
    views = [(src.frame(i).camera, src.frame(i).T_cam_from_world, src.frame(i).depth_m, src.label_map(i))
             for i in src.ids]
    truth = point_truth_labels(geom.points_m, views, src.n_classes, small_cfg.depth_max_m, 0.04)
    known = truth >= 0
    assert known.mean() > 0.8
    assert np.mean(geom.labels[known] == truth[known]) > 0.95, method
    # every class of the scene that covers a fair number of points is found
    present = [c for c in range(1, src.n_classes) if np.sum(truth == c) > 20]
    assert set(present) <= set(np.unique(geom.labels).tolist())
    np.testing.assert_allclose(geom.probs.sum(axis=1), 1.0, atol=1e-5)


@pytest.mark.parametrize("method", METHODS)
def test_reopen_and_extend_equals_one_pass(method: str, src: FrameSource, small_cfg: FuseConfig,
                                           tmp_path: Path) -> None:
    from cadalign.fuse.map_io import MapMeta

    cfg = _cfg(small_cfg, method)
    ids = list(src.ids)
    first = _fused(src, cfg, ids[:3])
    path = save_map(first, MapMeta(src.classes.names, ids[:3]), tmp_path / "map.npz")
    reopened, meta = load_map(path)
    assert meta.frame_ids == ids[:3] and reopened.frames_integrated == 3 and reopened.cfg == cfg
    np.testing.assert_array_equal(reopened.origin, first.origin)
    for i in ids[3:]:
        reopened.integrate(src.frame(i))
    whole = _fused(src, cfg, ids)
    a, b = reopened.extract_points(), whole.extract_points()
    assert len(a) == len(b)
    order_a, order_b = np.lexsort(a.points_m.T), np.lexsort(b.points_m.T)
    np.testing.assert_allclose(a.points_m[order_a], b.points_m[order_b], atol=1e-5)
    np.testing.assert_array_equal(a.labels[order_a], b.labels[order_b])


@pytest.mark.parametrize("method", METHODS)
def test_no_valid_depth_is_a_clear_error(method: str, src: FrameSource, small_cfg: FuseConfig) -> None:
    f = src.frame(src.ids[0])
    m = new_map(_cfg(small_cfg, method), src.n_classes)
    for bad in (np.zeros_like(f.depth_m), np.full_like(f.depth_m, np.nan), np.full_like(f.depth_m, 50.0)):
        with pytest.raises(InputError, match="no valid depth in"):
            m.integrate(dataclasses.replace(f, depth_m=bad))
    with pytest.raises(InputError, match="probabilities for 2 classes, the map 4"):
        m.integrate(dataclasses.replace(f, probs=f.probs[:2]))
    assert m.frames_integrated == 0
    with pytest.raises(InputError, match="empty|no surfel"):
        m.extract_points()


def test_bad_frame_shapes_are_refused(src: FrameSource) -> None:
    f = src.frame(src.ids[0])
    with pytest.raises(InputError, match="depth map has shape"):
        FuseFrame(f.depth_m[:10], f.probs, f.camera, f.T_cam_from_world)
    with pytest.raises(InputError, match="class probabilities must be"):
        FuseFrame(f.depth_m, f.probs[:, :10], f.camera, f.T_cam_from_world)


@pytest.mark.parametrize("method", METHODS)
def test_far_from_origin_world_keeps_precision(method: str, src: FrameSource, small_cfg: FuseConfig) -> None:
    """A world shifted by UTM-sized offsets gives the same map, shifted (float64 origin, float32 map)."""
    cfg = _cfg(small_cfg, method)
    block = cfg.voxel_m * cfg.block_resolution  # the origin snaps to blocks: same voxel grid in both worlds
    offset = np.round(np.array([5.0e6, 4.0e5, -200.0]) / block) * block
    T_shift = Rigid3(np.eye(3), -offset)  # world_near_from_world_far
    ids = list(src.ids)[:3]
    near = _fused(src, cfg, ids).extract_points()
    far_map = new_map(cfg, src.n_classes)
    for i in ids:
        f = src.frame(i)
        far_map.integrate(dataclasses.replace(f, T_cam_from_world=f.T_cam_from_world @ T_shift))
    far = far_map.extract_points()
    assert abs(len(far) - len(near)) <= 0.01 * len(near)
    assert np.all(np.abs(far_map.origin - offset) < 20)
    from scipy.spatial import cKDTree

    d = cKDTree(near.points_m).query(far.points_m - offset)[0]
    assert np.median(d) < 1e-3


def test_tsdf_weights_are_capped(src: FrameSource, small_cfg: FuseConfig) -> None:
    cfg = dataclasses.replace(small_cfg, weight_cap=3.0)
    m = new_map(cfg, src.n_classes)
    f = src.frame(src.ids[0])
    for _ in range(6):
        m.integrate(f)
    assert m.state()["weight"].max() == pytest.approx(3.0)


def test_old_open3d_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    import open3d as o3d

    from cadalign.fuse.tsdf import require_open3d

    monkeypatch.setattr(o3d, "__version__", "0.16.1")
    with pytest.raises(InputError, match="open3d 0.16.1 is too old"):
        require_open3d()

"""The fast (frustum) label path of the TSDF: bit-identical to the reference path, and its pieces on hand cases."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.fuse import tsdf_frustum, tsdf_labels
from cadalign.fuse.config import FuseConfig
from cadalign.fuse.inputs import FrameSource, open_source
from cadalign.fuse.tsdf import SemanticTSDF
from cadalign.fuse.tsdf_frustum import segments
from cadalign.fuse.tsdf_labels import band_offsets, band_pixels, block_cells, keys_of_cells, split_blocks


@pytest.fixture(scope="module")
def src(fuse_sim: Path) -> FrameSource:
    return open_source(fuse_sim)


def _sorted_state(m: SemanticTSDF) -> dict[str, np.ndarray]:
    s = m.state()
    order = np.lexsort(s["keys"].T)
    return {k: v[order] for k, v in s.items()}


def _fuse(src: FrameSource, cfg: FuseConfig) -> SemanticTSDF:
    m = SemanticTSDF(cfg, src.n_classes)
    for i in src.ids:
        m.integrate(src.frame(i))
    return m


@pytest.mark.parametrize("res, stride, threads, cell", [(8, 1, 1, 1), (4, 1, 2, 1), (4, 2, 3, 1), (8, 1, 2, 2)])
def test_frustum_labels_equal_the_reference_bit_for_bit(src: FrameSource, small_cfg: FuseConfig, res: int,
                                                        stride: int, threads: int, cell: int,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(tsdf_frustum, "MIN_SAMPLES_PER_THREAD", 1000)  # the tiny frames use the threads too
    # a small initial table: it grows (and moves every block) during the run, which the lookups must survive
    cfg = dataclasses.replace(small_cfg, block_resolution=res, block_count=300, label_pixel_stride=stride,
                              label_threads=threads, label_cell_voxels=cell)
    fast = _fuse(src, cfg)
    ref = _fuse(src, dataclasses.replace(cfg, label_lookup="reference"))
    a, b = _sorted_state(fast), _sorted_state(ref)
    assert a.keys() == b.keys()
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    assert np.any(a["label"] != 0)  # labels were written at all


def test_a_frame_spanning_too_many_blocks_falls_back_to_the_reference(src: FrameSource, small_cfg: FuseConfig,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    ref = _fuse(src, dataclasses.replace(small_cfg, label_lookup="reference"))
    monkeypatch.setattr(tsdf_labels, "MAX_TABLE_CELLS", 8)
    fallback = _fuse(src, small_cfg)
    np.testing.assert_array_equal(_sorted_state(fallback)["label"], _sorted_state(ref)["label"])


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(-(2**20), 2**20), min_size=3, max_size=30), st.integers(2, 16))
def test_split_blocks_is_floor_division(values: list[int], res: int) -> None:
    vox = np.array(values[: len(values) // 3 * 3], dtype=np.int32).reshape(3, -1)
    block, local = split_blocks(vox, res)
    np.testing.assert_array_equal(block, np.floor_divide(vox, res))
    loc = vox - np.floor_divide(vox, res) * res
    np.testing.assert_array_equal(local, loc[0] + res * (loc[1] + res * loc[2]))
    assert local.min(initial=0) >= 0 and local.max(initial=0) < res**3


def test_block_cells_round_trip_hand_case() -> None:
    blocks = np.array([[0, 0, -1, 3], [0, 0, 2, 0], [0, 1, 5, 0]], dtype=np.int32)  # (3, M)
    lo, shape = np.array([-1, 0, 0]), np.array([5, 3, 6])
    cells = block_cells(blocks, lo, shape)
    np.testing.assert_array_equal(cells, [(1 * 3 + 0) * 6 + 0, (1 * 3 + 0) * 6 + 1, (0 * 3 + 2) * 6 + 5, 4 * 3 * 6])
    np.testing.assert_array_equal(keys_of_cells(cells, lo, shape), blocks.T)


@pytest.mark.parametrize("n, p, parts", [(2, 10, 2), (1, 7, 2), (3, 5, 2), (2, 4, 3), (2, 3, 1)])
def test_segments_cover_the_samples_once_in_order(n: int, p: int, parts: int) -> None:
    runs = segments(n, p, parts)
    assert len(runs) == parts
    flat = [j * p + q for run in runs for j, p0, p1 in run for q in range(p0, p1)]
    assert flat == list(range(n * p))
    sizes = [sum(p1 - p0 for _, p0, p1 in run) for run in runs]
    assert max(sizes) - min(sizes) <= 1


def test_band_offsets_and_band_pixels() -> None:
    np.testing.assert_allclose(band_offsets(2.0, 0.02), [-0.01, 0.01])
    np.testing.assert_allclose(band_offsets(1.0, 0.02), [0.0])
    mask = np.ones((5, 6), bool)
    mask[0, 0] = False
    np.testing.assert_array_equal(band_pixels(mask, 2), [2, 4, 12, 14, 16, 24, 26, 28])


def test_color_every_skips_colour_only(src: FrameSource, small_cfg: FuseConfig) -> None:
    every = _sorted_state(_fuse(src, small_cfg))
    sparse = _sorted_state(_fuse(src, dataclasses.replace(small_cfg, color_every=3)))
    for name in ("keys", "tsdf", "weight", "label"):
        np.testing.assert_array_equal(sparse[name], every[name], err_msg=name)
    assert not np.array_equal(sparse["color"], every["color"])
    # still an average of observed colours (Open3D keeps them on a 0-255 scale)
    assert sparse["color"].min() >= 0 and sparse["color"].max() <= 255 + 1e-3 and sparse["color"].max() > 1


def test_realtime_preset_is_a_valid_tsdf_config() -> None:
    from cadalign.fuse.config import PRESETS

    rt = PRESETS["realtime"]
    assert rt.method == "tsdf" and rt.voxel_m == 0.02 and rt.block_resolution == 4 and rt.color_every > 1
    # the default scene's orbit needs ~196k 4^3 blocks: no table growth (seconds each) on the way
    assert rt.label_pixel_stride == 2 and rt.block_count >= 200_000
    assert rt.label_lookup == "frustum" and rt.trunc_voxels == PRESETS["default"].trunc_voxels


@pytest.mark.parametrize("lookup", ["frustum", "reference"])
def test_sparse_depth_off_open3d_grid_is_fused(lookup: str) -> None:
    """SfM-like depth: a few valid pixels, none on Open3D's every-4th-pixel grid (Open3D alone raised
    'No block is touched' and skipped such points); every point gets blocks and its label."""
    from cadalign.fuse.base import FuseFrame
    from cadalign.types import Camera, Rigid3

    size = 32
    cam = Camera(np.array([[size, 0, size / 2], [0, size, size / 2], [0, 0, 1]]), size, size)
    depth = np.zeros((size, size), np.float32)
    v, u = np.array([1, 5, 9, 13, 27]), np.array([3, 7, 14, 22, 30])  # off the 4-pixel grid
    depth[v, u] = 1.013
    probs = np.full((3, size, size), 0.0005, np.float32)
    probs[2] = 0.999
    m = SemanticTSDF(FuseConfig(voxel_m=0.05, block_count=64, label_lookup=lookup), 3)
    m.integrate(FuseFrame(depth, probs, cam, Rigid3()))
    assert m.n_blocks > 0
    label = m.state()["label"].reshape(-1, 3)
    labelled = label[(label != 0).any(axis=1)]
    # two samples (one voxel apart along the ray) per valid pixel, each in its own voxel, all saying class 2
    assert len(labelled) == 2 * len(u) and np.all(labelled.argmax(axis=1) == 2)


def test_band_pixels_phases_cover_every_pixel_once() -> None:
    mask = np.ones((5, 6), dtype=bool)
    mask[2, 3] = False
    seen = np.concatenate([band_pixels(mask, 2, phase) for phase in range(4)])
    np.testing.assert_array_equal(np.sort(seen), np.flatnonzero(mask))  # s^2 consecutive frames: each pixel once
    np.testing.assert_array_equal(band_pixels(mask, 2, 4), band_pixels(mask, 2, 0))
    np.testing.assert_array_equal(band_pixels(mask, 1, 3), np.flatnonzero(mask))


def test_label_stride_keeps_samples_within_two_voxels() -> None:
    from cadalign.fuse.tsdf_labels import label_stride

    z = np.full(100, 8.5)
    assert label_stride(2, 0.02, 457.0, z) == 2  # 640x480 at 8.5 m: 1.9 cm pixels, 2 cm voxels
    assert label_stride(2, 0.02, 228.5, z) == 1  # 320x240: 3.7 cm pixels, every pixel is needed
    assert label_stride(4, 0.02, 525.0, np.full(10, 1.0)) == 4  # near: the configured bound
    assert label_stride(1, 0.02, 457.0, z) == label_stride(3, 0.02, 457.0, z[:0]) == 1


def test_label_cell_voxels_must_divide_the_block() -> None:
    from cadalign.fuse.tsdf_labels import cell_holder

    with pytest.raises(ValueError, match="label_cell_voxels"):
        FuseConfig(label_cell_voxels=3)
    with pytest.raises(ValueError, match="label_cell_voxels"):
        FuseConfig(block_resolution=4, label_cell_voxels=8)
    vox = np.array([-3, -2, -1, 0, 1, 2, 3], np.int32)
    np.testing.assert_array_equal(cell_holder(vox, 2), [-4, -2, -2, 0, 0, 2, 2])

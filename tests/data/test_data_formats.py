"""COCO RLE, time-block splits and the torch datasets over a BOP scene."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from cadalign.errors import ConfigError, InputError
from cadalign.formats.bop import BopScene
from cadalign.formats.class_map import load_class_map
from cadalign.formats.coco import coco_annotations, mask_to_rle, rle_to_mask
from cadalign.formats.splits import time_block_splits
from cadalign.train.datasets import (
    DepthDataset,
    DetectionPoseDataset,
    SegmentationDataset,
    detection_collate,
)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(arrays(bool, st.tuples(st.integers(1, 12), st.integers(1, 12))))
def test_rle_round_trip(mask: np.ndarray) -> None:
    rle = mask_to_rle(mask)
    assert sum(rle["counts"]) == mask.size
    np.testing.assert_array_equal(rle_to_mask(rle), mask)


def test_rle_matches_coco_convention() -> None:
    m = np.array([[0, 1], [1, 1]], bool)  # column-major: 0,1,1,1 -> one zero then three ones
    assert mask_to_rle(m)["counts"] == [1, 3]
    assert mask_to_rle(np.ones((2, 2), bool))["counts"] == [0, 4]


@settings(max_examples=60, deadline=None, derandomize=True)
@given(n=st.integers(0, 400), block=st.integers(1, 30), gap=st.integers(0, 3), seed=st.integers(0, 5))
def test_time_blocks_are_disjoint_contiguous_and_separated(n: int, block: int, gap: int, seed: int) -> None:
    s = time_block_splits(range(n), block=block, gap=gap, seed=seed)
    owner = {}
    for name, ids in s.items():
        assert ids == sorted(ids)
        for i in ids:
            assert i not in owner
            owner[i] = name
    # frames of different splits are never closer than the gap (no near-duplicate leakage)
    labelled = sorted(owner)
    for a, b in zip(labelled, labelled[1:], strict=False):
        if owner[a] != owner[b]:
            assert b - a > gap
    n_blocks = -(-n // block)
    if n_blocks >= 8 and gap == 0:
        for name, frac in zip(("train", "val", "test"), (0.7, 0.15, 0.15), strict=True):
            assert abs(len(s[name]) / n - frac) <= block / n + 1.0 / n_blocks


def test_split_arguments_are_checked() -> None:
    with pytest.raises(ConfigError, match="sum"):
        time_block_splits(range(10), (0.5, 0.2, 0.2))
    with pytest.raises(ConfigError, match="block"):
        time_block_splits(range(10), block=0)


def test_coco_annotations_match_the_bop_masks(tiny_bop: Path) -> None:
    scene = BopScene(tiny_bop)
    cmap = load_class_map(tiny_bop)
    coco = coco_annotations(scene, scene.ids, cmap.class_of_obj, cmap.names)
    assert [c["name"] for c in coco["categories"]] == ["structure", "valve", "hot_stab"]
    assert len(coco["images"]) == 3 and len(coco["annotations"]) >= 3
    for a in coco["annotations"]:
        m = scene.mask(a["image_id"], a["gt_idx"])
        np.testing.assert_array_equal(rle_to_mask(a["segmentation"]), m)
        x, y, w, h = a["bbox"]
        assert m[y : y + h, x : x + w].sum() == a["area"] == m.sum()


def test_torch_datasets_agree_with_the_ground_truth(tiny_bop: Path) -> None:
    seg, dep, det = SegmentationDataset(tiny_bop), DepthDataset(tiny_bop, [1]), DetectionPoseDataset(tiny_bop)
    assert len(seg) == 3 and len(dep) == 1
    s = seg[0]
    assert s["image"].shape == (3, 120, 160) and s["image"].dtype == torch.float32
    assert 0.0 <= s["image"].min() and s["image"].max() <= 1.0
    assert set(torch.unique(s["label"]).tolist()) <= {0, 1, 2, 3} and (s["label"] > 0).any()
    d = dep[0]
    assert d["depth"].shape == (1, 120, 160) and torch.equal(d["valid"], d["depth"] > 0)
    np.testing.assert_allclose(d["depth"][0].numpy(), BopScene(tiny_bop).depth_m(1), atol=1e-6)
    item = det[0]
    n = len(item["labels"])
    assert n >= 1 and item["boxes"].shape == (n, 4) and item["masks"].shape == (n, 120, 160)
    for k in range(n):  # each box is the tight box of its mask; label = class of the obj_id
        ys, xs = torch.nonzero(item["masks"][k], as_tuple=True)
        assert item["boxes"][k].tolist() == [xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]
        assert item["labels"][k] == det.classes.class_of_obj[int(item["obj_ids"][k])]
        R = item["R"][k].double()
        assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-5)
    # segmentation labels painted from masks equal the class/ extras
    label_from_masks = torch.zeros(120, 160, dtype=torch.int64)
    for k in range(n):
        label_from_masks[item["masks"][k]] = item["labels"][k]
    assert torch.equal(label_from_masks, s["label"])
    batch = detection_collate([det[0], det[1]])
    assert batch["image"].shape == (2, 3, 120, 160) and len(batch["boxes"]) == 2


def test_missing_class_map_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="objects.json"):
        load_class_map(tmp_path)


def test_coco_from_the_instance_maps_equals_coco_from_mask_visib(tiny_bop: Path) -> None:
    """The build reads one instance/ PNG per frame for its COCO files, not every mask_visib PNG: the same file."""
    from functools import partial

    from cadalign.raycast.bop_writer import visible_masks

    scene = BopScene(tiny_bop)
    cmap = load_class_map(tiny_bop)
    fast = coco_annotations(scene, scene.ids, cmap.class_of_obj, cmap.names, partial(visible_masks, tiny_bop))
    assert fast == coco_annotations(scene, scene.ids, cmap.class_of_obj, cmap.names)
    assert len(fast["annotations"]) >= 3

"""Frame/unit conventions of the pose targets, end to end on simulated BOP ground truth.

The network's targets come from BOP files (mm, ``cam_R_m2c``/``cam_t_m2c``) through the dataset, the
resize to the network input, the training crops, each parameterisation's encode/decode and finally the
evaluation. GT poses fed through that chain must come back with ~0 error, and the CAD points projected
with them must land on the instance's visible mask (so neither the inverse pose, nor mm, nor a wrong K
could pass).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from pose_testutils import bop_items, doubled_frame, on_mask_fraction, tiny_cfg, well_visible

from cadalign.cad.symmetry import Symmetry
from cadalign.geometry import matrix_to_euler
from cadalign.geometry.torch_rotations import matrix_to_rotation_6d
from cadalign.metrics import pose as pm
from cadalign.models.maskrcnn import MaskRCNNPose
from cadalign.models.maskrcnn.detector import PoseRoIs
from cadalign.models.maskrcnn.pose_head import decode_pose, ego_to_allo, encode_translation
from cadalign.train.datasets import DetectionPoseDataset, detection_collate
from cadalign.train.pose import load_object_geometry, locate_dataset, targets_from_batch
from cadalign.train.pose_crop import crop_batch, crop_target, masks_to_boxes


def test_gt_pose_projects_onto_its_mask_in_metres(pose_bop: Path):
    ds = locate_dataset(pose_bop)
    geometry = load_object_geometry(ds.models_dir, 300)
    checked = 0
    for item in bop_items(pose_bop):
        for g in well_visible(item):
            assert on_mask_fraction(item, geometry, g) > 0.5
            # the inverse pose or millimetres put the model elsewhere
            Rt = item["R"].transpose(-1, -2)
            inv = {**item, "R": Rt, "t": -(Rt @ item["t"][..., None])[..., 0]}
            assert on_mask_fraction(inv, geometry, g) < 0.5
            mm = {**item, "t": item["t"] * 1000}
            assert on_mask_fraction(mm, geometry, g) < 0.5
            checked += 1
    assert checked >= 3


def test_resize_and_crop_keep_poses_consistent_with_pixels(pose_bop: Path):
    geometry, item, up, (h0, w0) = doubled_frame(pose_bop)
    assert torch.allclose(up["K"][:2, :3], 2 * item["K"][:2, :3])
    batch = detection_collate([up])
    g = torch.Generator().manual_seed(3)
    crop = crop_batch(batch, g, (h0, w0), object_prob=1.0)
    assert crop["image"].shape[-2:] == (h0, w0)
    for it in (up, targets_from_batch(crop)[0]):
        assert torch.equal(masks_to_boxes(it["masks"]), it["boxes"])
        for g_ in well_visible(it):
            assert on_mask_fraction(it, geometry, g_) > 0.5


def test_crop_shifts_principal_point_and_drops_empty_instances():
    masks = torch.zeros(2, 10, 12, dtype=torch.bool)
    masks[0, 1:3, 1:4] = True  # outside the crop below
    masks[1, 5:9, 6:12] = True
    t = {"masks": masks, "boxes": masks_to_boxes(masks), "labels": torch.tensor([1, 2]),
         "obj_ids": torch.tensor([4, 5]), "R": torch.eye(3).repeat(2, 1, 1), "t": torch.ones(2, 3),
         "K": torch.tensor([[10.0, 0, 6], [0, 10, 5], [0, 0, 1]])}
    out = crop_target(t, 4, 5, (6, 7))
    assert out["labels"].tolist() == [2] and out["obj_ids"].tolist() == [5]
    assert out["boxes"].tolist() == [[1.0, 1.0, 7.0, 5.0]]
    assert out["K"][0, 2] == 1 and out["K"][1, 2] == 1
    assert masks_to_boxes(masks).tolist() == [[1.0, 1.0, 4.0, 3.0], [6.0, 5.0, 12.0, 9.0]]


@pytest.mark.parametrize("param", ["thesis", "improved"])
def test_gt_poses_survive_encode_decode_and_the_evaluation(pose_bop: Path, param: str):
    """GT -> head targets -> decode_pose -> evaluation error ~0, for every instance of real frames."""
    n = 0
    for item in bop_items(pose_bop):
        R, t, K, boxes = item["R"].double(), item["t"].double(), item["K"].double(), item["boxes"].double()
        Ks = K.expand(len(R), 3, 3)
        if param == "thesis":
            raw = torch.cat([torch.as_tensor(matrix_to_euler(R.numpy(), "xyz")), t], 1)
        else:
            raw = torch.cat([matrix_to_rotation_6d(ego_to_allo(R, t)), encode_translation(t, Ks, boxes)], 1)
        R_dec, t_dec = decode_pose(raw, param, Ks, boxes)
        for i in range(len(R)):  # arccos of a float32-stored rotation: ~0.02 deg resolution near 0
            assert pm.rotation_error_deg(R_dec[i].numpy(), R[i].numpy()) < 0.05
            assert pm.translation_error_m(t_dec[i].numpy(), t[i].numpy()) < 1e-6 * max(1.0, float(t[i].norm()))
            n += 1
    assert n >= 3


def test_symmetry_aware_errors_are_zero_for_symmetric_equivalents():
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    R_gt = q * np.sign(np.linalg.det(q))
    th = 1.234
    Rz = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    cont = Symmetry.continuous((0.0, 0.0, 1.0))
    assert pm.rotation_error_deg(R_gt @ Rz, R_gt, cont) < 1e-4
    assert pm.rotation_error_deg(R_gt @ Rz, R_gt, Symmetry.none()) > 60
    # the discretised group (what the training loss samples) is within half a sampling step (0.5 deg)
    disc = Symmetry("discrete", tuple(cont.discretize(360)[1:]))
    assert pm.rotation_error_deg(R_gt @ Rz, R_gt, disc) < 0.6


def test_pose_targets_are_those_of_the_roi_s_own_object():
    """Each positive RoI's pose target is the pose of the ground-truth box it overlaps (not a neighbour's)."""
    torch.manual_seed(0)
    model = MaskRCNNPose(tiny_cfg(), ("background", "a", "b"))
    boxes = torch.tensor([[4.0, 4.0, 20.0, 20.0], [30.0, 10.0, 60.0, 40.0], [8.0, 26.0, 26.0, 46.0]])
    masks = torch.zeros(3, 48, 64, dtype=torch.bool)
    for i, b in enumerate(boxes.long().tolist()):
        masks[i, b[1]:b[3], b[0]:b[2]] = True
    t = torch.tensor([[1.0, 0, 5], [2.0, 0, 6], [3.0, 0, 7]])
    target = {"boxes": boxes, "labels": torch.tensor([1, 2, 1]), "masks": masks, "obj_ids": torch.tensor([7, 8, 9]),
              "R": torch.eye(3).repeat(3, 1, 1), "t": t, "K": torch.eye(3)}
    seen: list[PoseRoIs] = []

    def record(rois: PoseRoIs) -> dict[str, torch.Tensor]:
        seen.append(rois)
        return {"pose": rois.raw.sum() * 0}

    model.train()
    model(torch.rand(2, 3, 48, 64), [target, target], pose_loss=record)
    rois = seen[0]
    assert len(rois.boxes) >= 6  # at least the GT boxes themselves, in both images
    iou = pm.box_iou(rois.boxes.numpy(), boxes.numpy())
    best = iou.argmax(1)
    assert np.all(iou.max(1) >= 0.5)
    assert torch.equal(rois.t, t[best]) and torch.equal(rois.obj_ids, target["obj_ids"][best])
    assert torch.equal(rois.labels, target["labels"][best])


def test_crop_augment_is_seeded_and_config_checked(pose_bop: Path):
    from cadalign.config import from_dict
    from cadalign.errors import ConfigError
    from cadalign.train.augment import AugmentConfig
    from cadalign.train.pose import PRESETS, PoseTrainConfig, make_augment

    ds = locate_dataset(pose_bop)
    data = DetectionPoseDataset(ds.scene_dir, ds.splits["train"][:2])
    batch = detection_collate([data[0], data[1]])
    aug = make_augment(AugmentConfig(enabled=False), (60, 80))
    a = aug(batch, torch.Generator().manual_seed(5))
    b = aug(batch, torch.Generator().manual_seed(5))
    assert a["image"].shape == (2, 3, 60, 80) and torch.equal(a["image"], b["image"])
    assert all(torch.equal(x, y) for x, y in zip(a["K"], b["K"], strict=True))
    assert make_augment(AugmentConfig(enabled=False)) is None
    with pytest.raises(ConfigError, match="crop_hw"):
        from_dict(PoseTrainConfig, {"crop_hw": [500, 320]}, base=PRESETS["fast"])
    with pytest.raises(ValueError, match="larger than the training images"):
        crop_batch(batch, torch.Generator(), (200, 80))


def test_pose_head_input_is_invariant_to_crops_and_resizes():
    """The head sees the RoI in normalised camera coordinates: a crop or a 2x resize (K moving along) is no change."""
    from cadalign.models.maskrcnn.pose_head import PoseHead

    torch.manual_seed(0)
    head = PoseHead(8, 14, 8, 16, 2, "thesis").eval()
    torch.nn.init.normal_(head.out.weight, std=1.0)  # the head starts nearly constant
    feats = torch.randn(1, 8, 14, 14)
    K = torch.tensor([[[300.0, 0, 160], [0, 300, 120], [0, 0, 1]]])
    box = torch.tensor([[100.0, 50, 140, 90]])
    Kc = K.clone()
    Kc[:, 0, 2] -= 30
    Kc[:, 1, 2] -= 20
    Ks = K.clone()
    Ks[:, :2] *= 2
    with torch.no_grad():
        ref = head(feats, box, K)
        assert torch.allclose(head(feats, box - torch.tensor([30.0, 20, 30, 20]), Kc), ref, atol=1e-6)
        assert torch.allclose(head(feats, box * 2, Ks), ref, atol=1e-6)
        assert not torch.allclose(head(feats, box + 40, K), ref, atol=1e-4)

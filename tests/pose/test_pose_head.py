"""Pose parameterisations (encode/decode, allocentric), the pose losses and the CAD model loader."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.cad.symmetry import Symmetry
from cadalign.geometry import euler_to_matrix, random_rotation
from cadalign.geometry.torch_rotations import geodesic_angle, matrix_to_rotation_6d
from cadalign.models.maskrcnn.detector import PoseRoIs
from cadalign.models.maskrcnn.pose_head import (
    PoseHead,
    allo_to_ego,
    decode_pose,
    decode_translation,
    ego_to_allo,
    encode_translation,
    euler_xyz_to_matrix,
    ray_rotation,
)
from cadalign.train.pose import load_object_geometry, symmetry_from_bop
from cadalign.train.pose_losses import ObjectGeometry, PoseLoss, PoseLossConfig

K = torch.tensor([[500.0, 0, 320], [0, 480, 240], [0, 0, 1]], dtype=torch.float64)


@settings(max_examples=25, deadline=None)
@given(x=st.floats(-3, 3), y=st.floats(-2, 2), z=st.floats(0.2, 40), bx=st.floats(0, 600), by=st.floats(0, 400),
       bw=st.floats(1, 300), bh=st.floats(1, 300), s=st.floats(0.1, 4))
def test_translation_code_round_trip_and_resize_invariance(x, y, z, bx, by, bw, bh, s):
    t = torch.tensor([[x, y, z]], dtype=torch.float64)
    box = torch.tensor([[bx, by, bx + bw, by + bh]], dtype=torch.float64)
    code = encode_translation(t, K[None], box)
    torch.testing.assert_close(decode_translation(code, K[None], box), t, rtol=1e-9, atol=1e-9)
    # resizing the image by s scales K's first two rows and the box: the code is unchanged (scale-invariant)
    Ks = torch.diag(torch.tensor([s, s, 1.0], dtype=torch.float64)) @ K
    torch.testing.assert_close(encode_translation(t, Ks[None], box * s), code, rtol=1e-9, atol=1e-9)


def test_translation_code_hand_case():
    # object on the optical axis at 4 m, RoI of 100 x 50 px centred on the principal point: (0, 0, 4*100/500)
    t = torch.tensor([[0.0, 0.0, 4.0]], dtype=torch.float64)
    box = torch.tensor([[270.0, 215.0, 370.0, 265.0]], dtype=torch.float64)
    torch.testing.assert_close(encode_translation(t, K[None], box), torch.tensor([[0.0, 0.0, 0.8]],
                                                                                   dtype=torch.float64))


def test_allocentric_round_trip_and_ray_rotation():
    rng = np.random.default_rng(0)
    R = torch.tensor(random_rotation(rng, 20))
    t = torch.tensor(rng.normal(size=(20, 3)) + [0, 0, 5])
    torch.testing.assert_close(allo_to_ego(ego_to_allo(R, t), t), R)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(ray_rotation(t) @ z, t / t.norm(dim=1, keepdim=True))
    # on the optical axis the allocentric and egocentric rotations coincide
    torch.testing.assert_close(ray_rotation(torch.tensor([[0, 0, 3.0]], dtype=torch.float64))[0],
                               torch.eye(3, dtype=torch.float64))
    # an object translated sideways keeps its appearance: same allocentric rotation as a rotated camera sees
    Rc = ray_rotation(t)
    torch.testing.assert_close(ego_to_allo(Rc @ R, t), R)


def test_euler_matches_numpy_and_thesis_decode():
    ang = np.random.default_rng(1).uniform(-3, 3, (10, 3))
    torch.testing.assert_close(euler_xyz_to_matrix(torch.tensor(ang)), torch.tensor(euler_to_matrix(ang, "xyz")))
    raw = torch.cat([torch.tensor(ang), torch.tensor([[0.1, 0.2, 3.0]]).double().expand(10, 3)], 1)
    R, t = decode_pose(raw, "thesis", K.expand(10, 3, 3), torch.zeros(10, 4, dtype=torch.float64))
    torch.testing.assert_close(R, torch.tensor(euler_to_matrix(ang, "xyz")))
    assert torch.equal(t, raw[:, 3:])


def test_pose_head_starts_at_identity_and_is_class_specific():
    head = PoseHead(8, 14, 8, 16, num_classes=3, param="improved")
    with torch.no_grad():
        raw = head(torch.randn(5, 8, 14, 14), torch.tensor([[0, 0, 10, 10.0]]).expand(5, 4), K.float().expand(5, 3, 3))
    assert raw.shape == (5, 3, 9)
    R, t = decode_pose(raw[:, 1], "improved", K.float().expand(5, 3, 3), torch.tensor([[0, 0, 10, 10.0]] * 5))
    allo = ego_to_allo(R, t)
    assert float(geodesic_angle(allo, torch.eye(3).expand(5, 3, 3)).max()) < 0.05
    thesis = PoseHead(8, 14, 8, 16, 2, "thesis")
    assert thesis(torch.randn(2, 8, 14, 14), torch.zeros(2, 4), K.float().expand(2, 3, 3)).shape == (2, 2, 6)


def _geometry(sym: Symmetry) -> ObjectGeometry:
    pts = np.random.default_rng(3).uniform(-0.2, 0.2, (100, 3))
    pts[:, 2] *= 3  # elongated along z, not symmetric by itself
    return ObjectGeometry(pts, 1.0, sym)


def _rois(R_pred: torch.Tensor, R_gt: torch.Tensor, t: torch.Tensor, obj: list[int], param: str = "improved"):
    n = len(obj)
    box = torch.tensor([[250.0, 200, 350, 290]]).expand(n, 4)
    Kf = K.float().expand(n, 3, 3)
    if param == "improved":
        raw = torch.cat([matrix_to_rotation_6d(ego_to_allo(R_pred, t)), encode_translation(t, Kf, box)], 1)
    else:
        raw = torch.zeros(n, 6)
    return PoseRoIs(raw, box, torch.ones(n, dtype=torch.int64), torch.tensor(obj), R_gt, t, Kf, param)


def test_point_matching_loss_is_symmetry_aware():
    loss = PoseLoss({1: _geometry(Symmetry.none()), 2: _geometry(Symmetry.cyclic([0, 0, 1], 2)),
                     3: _geometry(Symmetry.continuous([0, 0, 1]))}, PoseLossConfig(continuous_samples=36))
    R_gt = torch.tensor(random_rotation(np.random.default_rng(4), 3), dtype=torch.float32)
    t = torch.tensor([[0.3, -0.1, 4.0]] * 3)
    flip = torch.tensor(Symmetry.cyclic([0, 0, 1], 2).discrete[0][:3, :3], dtype=torch.float32)
    # the exact pose costs nothing for every object
    exact = loss(_rois(R_gt, R_gt, t, [1, 2, 3]))
    assert float(exact["pose_rot"]) < 1e-6 and float(exact["pose_trans"]) < 1e-6
    # a 180 deg flip about z is free only for the symmetric objects
    pm = loss.point_matching(R_gt @ flip, R_gt, torch.tensor([1, 2, 3]))
    assert pm[0] > 0.05 and pm[1] < 1e-6 and pm[2] < 1e-6
    # an off-grid 51.5 deg turn about the continuous axis costs only its 1.5 deg distance to the 10 deg grid
    off = torch.tensor(Symmetry.continuous([0, 0, 1]).discretize(720)[103][:3, :3], dtype=torch.float32)
    pm = loss.point_matching(R_gt[:2] @ off, R_gt[:2], torch.tensor([3, 1]))
    assert pm[0] < 0.05 * pm[1]
    with pytest.raises(Exception, match="object id 9"):
        loss.point_matching(R_gt[:1], R_gt[:1], torch.tensor([9]))


def test_thesis_loss_is_l1_to_euler_and_translation():
    loss = PoseLoss({1: _geometry(Symmetry.none())}, PoseLossConfig())
    ang = np.array([[0.1, -0.2, 0.3]])
    R = torch.tensor(euler_to_matrix(ang, "xyz"), dtype=torch.float32)
    rois = _rois(R, R, torch.tensor([[0.0, 0.0, 2.0]]), [1], "thesis")
    rois.raw = torch.tensor([[0.1, -0.2, 0.3, 0.0, 0.0, 2.0]], requires_grad=True)
    assert float(loss(rois)["pose_l1"].detach()) < 1e-6
    rois.raw = torch.tensor([[0.1, -0.2, 0.3, 0.6, 0.0, 2.0]], requires_grad=True)
    out = loss(rois)["pose_l1"]
    assert float(out.detach()) == pytest.approx(0.1)
    out.backward()
    assert rois.raw.grad is not None and float(rois.raw.grad.abs().sum()) > 0


def test_symmetry_from_bop_converts_mm():
    entry = {"symmetries_continuous": [{"axis": [0, 0, 2], "offset": [0, 0, 100]}],
             "symmetries_discrete": [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 50, 0, 0, 0, 1]]}
    sym = symmetry_from_bop(entry)
    assert sym.kind == "continuous"
    np.testing.assert_allclose(sym.axis, [0, 0, 1])
    np.testing.assert_allclose(sym.offset_m, [0, 0, 0.1])
    np.testing.assert_allclose(sym.discrete[0][2, 3], 0.05)
    assert symmetry_from_bop({}).kind == "none"


def test_load_object_geometry_in_metres(pose_bop: Path):
    models = pose_bop.parent.parent / "models"
    geo = load_object_geometry(models, 50, seed=0)
    info = json.loads((models / "models_info.json").read_text())
    assert sorted(geo) == sorted(int(k) for k in info)
    for oid, g in geo.items():
        assert g.points_m.shape == (50, 3)
        assert g.diameter_m == pytest.approx(info[str(oid)]["diameter"] / 1000)
        span = np.linalg.norm(g.points_m[:, None] - g.points_m[None], axis=-1).max()  # surface samples, metres
        assert 0.2 * g.diameter_m < span <= g.diameter_m * 1.0001


def test_rois_with_the_object_origin_far_outside_are_left_out():
    loss = PoseLoss({1: _geometry(Symmetry.none())}, PoseLossConfig(max_center_offset=1.5))
    R = torch.eye(3).expand(2, 3, 3)
    rois = _rois(R, R, torch.tensor([[0.0, 0.0, 2.0]] * 2), [1, 1])
    rois.raw = rois.raw + 0.3  # a wrong prediction for both RoIs
    both = loss(rois)
    # the second RoI is a 10 px box 100 px left of the projected origin (dx = 10): only the first one counts
    rois.boxes = torch.tensor([[250.0, 200, 350, 290], [210, 235, 220, 245]])
    one = loss(rois)
    assert float(one["pose_trans"]) > 0
    rois.boxes = torch.tensor([[210.0, 235, 220, 245]] * 2)
    none = loss(rois)
    assert float(none["pose_rot"]) == 0 and float(none["pose_trans"]) == 0
    assert float(both["pose_rot"]) > 0

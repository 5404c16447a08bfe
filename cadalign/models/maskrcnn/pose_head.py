"""The per-RoI 6-DoF pose head and its two parameterisations.

``thesis`` (the seed's baseline, 6 values): extrinsic ``xyz`` Euler angles (radians, scipy's convention,
``R = Rz(c) Ry(b) Rx(a)``) and the translation in metres, regressed directly.

``improved`` (9 values, CDPN / GDR-Net): an *allocentric* rotation in the 6D continuous representation
(Zhou et al. 2019) and a scale-invariant translation relative to the RoI:

- ``dx = (u - bx) / bw``, ``dy = (v - by) / bh``: the projected object origin ``(u, v) = pi(K t)`` relative
  to the RoI centre ``(bx, by)`` in units of the RoI size ``(bw, bh)``;
- ``dz = t_z * s / fx`` with ``s = max(bw, bh)``: depth normalised by the RoI zoom (``fx / s`` is how many
  focal lengths the RoI spans), so it is the object's metric extent, independent of distance and camera.

The allocentric rotation is the egocentric one with the viewing-ray rotation removed:
``R_ego = R_ray(t) R_allo`` where ``R_ray`` turns the optical axis ``z`` onto the ray through the object
origin. It depends only on the object's appearance in the RoI, which is what the RoI features see.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cadalign.geometry.torch_rotations import axis_angle_to_matrix, rotation_6d_to_matrix

PoseParam = Literal["thesis", "improved"]
POSE_DIMS: dict[str, int] = {"thesis": 6, "improved": 9}
"""Raw output values per class and RoI for each parameterisation."""


def ray_rotation(t: Tensor) -> Tensor:
    """``(..., 3, 3)`` rotation taking the optical axis ``(0, 0, 1)`` onto the direction of ``t (..., 3)``."""
    d = t / torch.linalg.vector_norm(t, dim=-1, keepdim=True).clamp_min(1e-12)
    axis = torch.stack([-d[..., 1], d[..., 0], torch.zeros_like(d[..., 0])], -1)  # z x d
    s = torch.linalg.vector_norm(axis, dim=-1, keepdim=True)
    angle_over_sin = torch.where(s > 1e-9, torch.atan2(s, d[..., 2:]) / s.clamp_min(1e-12), torch.ones_like(s))
    return axis_angle_to_matrix(axis * angle_over_sin)


def allo_to_ego(R_allo: Tensor, t: Tensor) -> Tensor:
    """Egocentric rotations ``(..., 3, 3)`` from allocentric ones at translations ``t (..., 3)``."""
    return ray_rotation(t) @ R_allo


def ego_to_allo(R_ego: Tensor, t: Tensor) -> Tensor:
    """Allocentric rotations ``(..., 3, 3)``: the inverse of :func:`allo_to_ego`."""
    return ray_rotation(t).transpose(-1, -2) @ R_ego


def _box_geometry(boxes: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    bw = (boxes[:, 2] - boxes[:, 0]).clamp_min(1e-3)
    bh = (boxes[:, 3] - boxes[:, 1]).clamp_min(1e-3)
    return (boxes[:, 0] + boxes[:, 2]) / 2, (boxes[:, 1] + boxes[:, 3]) / 2, bw, bh, torch.maximum(bw, bh)


def encode_translation(t: Tensor, K: Tensor, boxes: Tensor) -> Tensor:
    """Scale-invariant translation ``(R, 3)`` = ``(dx, dy, dz)`` of ``t (R, 3)`` metres, ``K (R, 3, 3)``, boxes px."""
    uvw = (K @ t[:, :, None])[:, :, 0]
    u, v = uvw[:, 0] / uvw[:, 2], uvw[:, 1] / uvw[:, 2]
    bx, by, bw, bh, s = _box_geometry(boxes)
    return torch.stack([(u - bx) / bw, (v - by) / bh, t[:, 2] * s / K[:, 0, 0]], 1)


def decode_translation(code: Tensor, K: Tensor, boxes: Tensor) -> Tensor:
    """Translation ``(R, 3)`` in metres from ``(dx, dy, dz)`` codes: the inverse of :func:`encode_translation`."""
    bx, by, bw, bh, s = _box_geometry(boxes)
    z = code[:, 2] * K[:, 0, 0] / s
    uv1 = torch.stack([bx + code[:, 0] * bw, by + code[:, 1] * bh, torch.ones_like(bx)], 1)
    return z[:, None] * torch.linalg.solve(K, uv1[:, :, None])[:, :, 0]


def euler_xyz_to_matrix(angles: Tensor) -> Tensor:
    """``(..., 3, 3)`` from extrinsic ``xyz`` Euler angles ``(..., 3)`` (radians): ``Rz(c) Ry(b) Rx(a)``."""
    a, b, c = angles.unbind(-1)
    o, i = torch.zeros_like(a), torch.ones_like(a)

    def rot(rows: list[list[Tensor]]) -> Tensor:
        return torch.stack([torch.stack(r, -1) for r in rows], -2)

    rx = rot([[i, o, o], [o, a.cos(), -a.sin()], [o, a.sin(), a.cos()]])
    ry = rot([[b.cos(), o, b.sin()], [o, i, o], [-b.sin(), o, b.cos()]])
    rz = rot([[c.cos(), -c.sin(), o], [c.sin(), c.cos(), o], [o, o, i]])
    return rz @ ry @ rx


def decode_pose(raw: Tensor, param: PoseParam, K: Tensor, boxes: Tensor) -> tuple[Tensor, Tensor]:
    """``(R_cam_from_obj (R, 3, 3), t_cam_from_obj_m (R, 3))`` from raw head outputs ``(R, D)``.

    ``K`` (R, 3, 3) and ``boxes`` (R, 4) px are those of the image the head saw (after any resize).
    """
    if param == "thesis":
        return euler_xyz_to_matrix(raw[:, :3]), raw[:, 3:6]
    t = decode_translation(raw[:, 6:9], K, boxes)
    return allo_to_ego(rotation_6d_to_matrix(raw[:, :6]), t), t


class PoseHead(nn.Module):
    """Convs on the RoI features + the RoI box in normalised camera coordinates -> raw pose ``(R, C, D)``.

    The RoI box ``((x - cx) / fx, (y - cy) / fy)`` of both corners is appended to the FC input so the ``thesis``
    head, which regresses absolute translations, knows the RoI's viewing ray and angular size. These are
    independent of image crops and resizes (K moves with them), unlike pixel positions divided by the image size.
    """

    def __init__(self, channels: int, pool: int, width: int, rep: int, num_classes: int, param: PoseParam) -> None:
        super().__init__()
        self.param, self.num_classes, self.dims = param, num_classes, POSE_DIMS[param]
        self.convs = nn.Sequential(
            nn.Conv2d(channels, width, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(width, width, 3, padding=1), nn.ReLU(inplace=True),
            nn.Conv2d(width, width, 3, stride=2, padding=1), nn.ReLU(inplace=True),
        )
        side = (pool + 1) // 2
        self.fc1 = nn.Linear(width * side * side + 4, rep)
        self.fc2 = nn.Linear(rep, rep)
        self.out = nn.Linear(rep, num_classes * self.dims)
        nn.init.normal_(self.out.weight, std=0.001)
        bias = torch.zeros(num_classes, self.dims)
        if param == "improved":
            bias[:, :6] = torch.tensor([1.0, 0, 0, 0, 1.0, 0])  # start at the identity (allocentric) rotation
            bias[:, 8] = 1.0  # ~1 m object extent
        else:
            bias[:, 5] = 3.0  # ~3 m in front of the camera
        with torch.no_grad():
            self.out.bias.copy_(bias.reshape(-1))

    def forward(self, feats: Tensor, boxes: Tensor, K: Tensor) -> Tensor:
        """``feats`` (R, C, P, P) RoI features, ``boxes`` (R, 4) px and ``K`` (R, 3, 3) of the image the RoIs are in."""
        f = torch.stack([K[:, 0, 0], K[:, 1, 1], K[:, 0, 0], K[:, 1, 1]], 1)
        c = torch.stack([K[:, 0, 2], K[:, 1, 2], K[:, 0, 2], K[:, 1, 2]], 1)
        geo = (boxes - c) / f
        x = self.convs(feats).flatten(1)
        x = F.relu(self.fc2(F.relu(self.fc1(torch.cat([x, geo], 1)))))
        return self.out(x).view(-1, self.num_classes, self.dims)

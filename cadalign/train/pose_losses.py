"""Pose losses of the detection + pose network, for both parameterisations.

- ``thesis``: L1 on ``(Euler xyz (rad), t (m))`` against the ground truth's Euler angles and translation.
- ``improved``: a symmetry-aware point-matching loss on the rotation (Wang et al. / GDR-Net)::

      L_R = min_{S in sym(obj)} mean_p | R_pred p - R_gt (S p) |_1 / diameter

  over CAD points ``p`` (metres), where ``R_pred`` is the predicted allocentric rotation turned egocentric
  along the *ground-truth* viewing ray (so the rotation loss does not depend on the translation estimate),
  plus L1 on the scale-invariant translation codes ``(dx, dy, dz)`` of
  :func:`cadalign.models.maskrcnn.pose_head.encode_translation`, the ``dz`` term (metres of object extent)
  divided by the object's diameter so that a 15 m frame does not outweigh a 0.1 m valve. A continuous
  symmetry is sampled as rotations about its axis (``continuous_samples``), so the minimum is within
  ``pi / n`` of the true one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from cadalign.cad.symmetry import Symmetry
from cadalign.config import bounded
from cadalign.errors import InputError
from cadalign.geometry import matrix_to_euler
from cadalign.geometry.torch_rotations import rotation_6d_to_matrix
from cadalign.models.maskrcnn.detector import PoseRoIs
from cadalign.models.maskrcnn.pose_head import allo_to_ego, encode_translation


@dataclass(frozen=True)
class PoseLossConfig:
    rotation_weight: float = bounded(1.0, ge=0)
    """Weight of the point-matching rotation loss (``improved``)."""
    translation_weight: float = bounded(1.0, ge=0)
    """Weight of the L1 loss on the translation codes (``improved``)."""
    thesis_weight: float = bounded(1.0, ge=0)
    """Weight of the 6-value L1 loss (``thesis``)."""
    continuous_samples: int = bounded(36, ge=1)
    """Rotations sampled about a continuous symmetry axis."""
    max_center_offset: float = bounded(1.5, gt=0)
    """RoIs whose true projected object origin is more than this many RoI sizes from the RoI centre (``|dx|`` or
    ``|dy|``) are left out of the pose loss (both parameterisations): the visible piece is too small a part of
    the object (a truncated or heavily occluded structure) for the RoI features to place it."""


@dataclass(frozen=True)
class ObjectGeometry:
    """What the pose loss knows about one object: ``points_m`` (P, 3), ``diameter_m``, its symmetry."""

    points_m: np.ndarray
    diameter_m: float
    symmetry: Symmetry


class PoseLoss:
    """``PoseRoIs -> {"pose_rot", "pose_trans"}`` (improved) or ``{"pose_l1"}`` (thesis).

    Args:
        objects: BOP obj_id -> geometry; every obj_id of the training set must be present.
        cfg: weights and symmetry sampling.
    """

    def __init__(self, objects: dict[int, ObjectGeometry], cfg: PoseLossConfig) -> None:
        if not objects:
            raise InputError("the pose loss needs the CAD points of at least one object (models/ is empty?)")
        self.cfg = cfg
        self.ids = sorted(objects)
        self._row = {oid: i for i, oid in enumerate(self.ids)}
        n_pts = min(len(objects[o].points_m) for o in self.ids)
        syms = [objects[o].symmetry.discretize(cfg.continuous_samples) for o in self.ids]
        n_sym = max(len(s) for s in syms)
        # pad every object's symmetry list to the same length by repeating the identity (the min is unchanged)
        mats = np.stack([np.stack(s + [np.eye(4)] * (n_sym - len(s))) for s in syms])
        self.points = torch.tensor(np.stack([objects[o].points_m[:n_pts] for o in self.ids]), dtype=torch.float32)
        self.sym = torch.tensor(mats, dtype=torch.float32)  # (O, S, 4, 4)
        self.diameter = torch.tensor([max(objects[o].diameter_m, 1e-6) for o in self.ids], dtype=torch.float32)

    def rows(self, obj_ids: Tensor) -> Tensor:
        """Row of each obj_id in the loss tables; an unknown id is an error naming it."""
        try:
            return torch.tensor([self._row[int(o)] for o in obj_ids.tolist()], dtype=torch.int64)
        except KeyError as exc:
            raise InputError(f"object id {exc.args[0]} has no CAD model in the dataset's models/ folder; "
                             "rebuild the dataset's models/ (models_info.json + obj_XXXXXX.ply)") from exc

    def point_matching(self, R_pred: Tensor, R_gt: Tensor, obj_ids: Tensor) -> Tensor:
        """Symmetry-aware point-matching distance ``(P,)`` of each RoI, in object diameters."""
        dev = R_pred.device
        rows = self.rows(obj_ids).to(dev)
        pts = self.points.to(dev)[rows]  # (P, N, 3)
        sym = self.sym.to(dev)[rows]  # (P, S, 4, 4)
        sym_pts = pts[:, None] @ sym[..., :3, :3].transpose(-1, -2) + sym[:, :, None, :3, 3]  # (P, S, N, 3)
        gt = sym_pts @ R_gt[:, None].transpose(-1, -2)
        pred = (pts @ R_pred.transpose(-1, -2))[:, None]
        dist = (pred - gt).abs().sum(-1).mean(-1)  # (P, S)
        return dist.min(dim=1).values / self.diameter.to(dev)[rows]

    def __call__(self, rois: PoseRoIs) -> dict[str, Tensor]:
        code = encode_translation(rois.t, rois.K, rois.boxes)
        keep = (code[:, :2].abs() <= self.cfg.max_center_offset).all(1)
        raw, R_gt, t_gt, code, obj = rois.raw[keep], rois.R[keep], rois.t[keep], code[keep], rois.obj_ids[keep]
        if raw.shape[0] == 0:
            zero = rois.raw.sum() * 0
            return {"pose_l1": zero} if rois.param == "thesis" else {"pose_rot": zero, "pose_trans": zero}
        if rois.param == "thesis":
            euler = torch.as_tensor(matrix_to_euler(R_gt.detach().double().cpu().numpy(), "xyz"),
                                    dtype=raw.dtype, device=raw.device)
            target = torch.cat([euler, t_gt], 1)
            return {"pose_l1": self.cfg.thesis_weight * (raw - target).abs().mean()}
        R_pred = allo_to_ego(rotation_6d_to_matrix(raw[:, :6]), t_gt)
        rot = self.point_matching(R_pred, R_gt, obj).mean()
        diam = self.diameter.to(raw.device)[self.rows(obj).to(raw.device)]
        err = (raw[:, 6:9] - code).abs()
        trans = (err[:, 0] + err[:, 1] + err[:, 2] / diam).mean() / 3
        return {"pose_rot": self.cfg.rotation_weight * rot, "pose_trans": self.cfg.translation_weight * trans}

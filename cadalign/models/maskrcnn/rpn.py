"""Region proposal network: objectness + box deltas per anchor, proposals by NMS, and its losses.

Also holds the box matcher and the balanced sampler shared with the RoI heads (torchvision's rules).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cadalign.models.maskrcnn.anchors import flatten_level, grid_anchors
from cadalign.models.ops import batched_nms, box_iou, clip_boxes, decode_boxes, encode_boxes

BELOW, BETWEEN = -1, -2
"""Match codes: background (IoU below the low threshold) and ignored (between the thresholds)."""


def match(iou: Tensor, high: float, low: float, allow_low_quality: bool) -> Tensor:
    """For each prediction (column of ``iou (G, P)``) the matched target index, or BELOW / BETWEEN.

    With ``allow_low_quality`` each target also claims the predictions with which it has its highest IoU
    (even below ``high``), so every ground-truth box gets at least one positive anchor.
    """
    if iou.shape[0] == 0:
        return torch.full((iou.shape[1],), BELOW, dtype=torch.int64, device=iou.device)
    vals, matches = iou.max(dim=0)
    all_matches = matches.clone()
    matches[vals < low] = BELOW
    matches[(vals >= low) & (vals < high)] = BETWEEN
    if allow_low_quality:
        best = iou.max(dim=1).values
        pred = torch.nonzero((iou == best[:, None]) & (best[:, None] > 0))[:, 1]
        matches[pred] = all_matches[pred]
    return matches


def sample(is_pos: Tensor, is_neg: Tensor, batch: int, pos_fraction: float,
           order: Callable[[Tensor], Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Random positive and negative indices: at most ``batch * pos_fraction`` positives, ``batch`` in all.
    ``order``, when given, reorders the shuffled positive indices before the first ones are taken."""
    pos = torch.nonzero(is_pos).squeeze(1)
    neg = torch.nonzero(is_neg).squeeze(1)
    n_pos = min(int(batch * pos_fraction), pos.numel())
    n_neg = min(batch - n_pos, neg.numel())
    pos = pos[torch.randperm(pos.numel(), device=pos.device)]
    if order is not None and pos.numel():
        pos = order(pos)
    pos = pos[:n_pos]
    neg = neg[torch.randperm(neg.numel(), device=neg.device)[:n_neg]]
    return pos, neg


@dataclass(frozen=True)
class RPNSettings:
    """RPN hyper-parameters (a plain record built by the detector from its config)."""

    sizes: tuple[float, ...]
    ratios: tuple[float, ...]
    strides: tuple[int, ...]
    pre_nms_train: int
    post_nms_train: int
    pre_nms_test: int
    post_nms_test: int
    nms_thresh: float = 0.7
    fg_iou: float = 0.7
    bg_iou: float = 0.3
    batch_per_image: int = 256
    pos_fraction: float = 0.5
    min_size: float = 1e-3
    scales: tuple[float, ...] = (1.0,)


class RPN(nn.Module):
    """Shared 3x3 conv head over all levels; proposals and (in training) losses."""

    def __init__(self, channels: int, s: RPNSettings) -> None:
        super().__init__()
        self.s = s
        a = len(s.ratios) * len(s.scales)
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)
        self.cls = nn.Conv2d(channels, a, 1)
        self.box = nn.Conv2d(channels, 4 * a, 1)
        for m in (self.conv, self.cls, self.box):
            nn.init.normal_(m.weight, std=0.01)
            nn.init.zeros_(m.bias)

    def forward(self, feats: list[Tensor], image_hw: tuple[int, int], gt_boxes: list[Tensor] | None = None
                ) -> tuple[list[Tensor], dict[str, Tensor]]:
        """Proposals per image ``(P, 4)`` (detached) and the RPN losses when ``gt_boxes`` is given."""
        logits, deltas, anchors, counts = [], [], [], []
        for f, stride, size in zip(feats, self.s.strides, self.s.sizes, strict=True):
            t = F.relu(self.conv(f))
            logits.append(flatten_level(self.cls(t), 1).squeeze(-1))
            deltas.append(flatten_level(self.box(t), 4))
            anchors.append(self._level_anchors(f, stride, size))
            counts.append(anchors[-1].shape[0])
        logit, delta, anc = torch.cat(logits, 1), torch.cat(deltas, 1), torch.cat(anchors, 0)
        proposals = self._proposals(logit.detach(), delta.detach(), anc, counts, image_hw)
        losses = {} if gt_boxes is None else self._losses(logit, delta, anc, gt_boxes)
        return proposals, losses

    def _level_anchors(self, f: Tensor, stride: int, size: float) -> Tensor:
        return grid_anchors(tuple(f.shape[-2:]), stride, [size * k for k in self.s.scales], self.s.ratios, f.device)

    def anchors(self, feats: list[Tensor]) -> Tensor:
        """``(A, 4)`` the anchors of every level of ``feats``, in the order of the RPN's outputs."""
        return torch.cat([self._level_anchors(f, stride, size)
                          for f, stride, size in zip(feats, self.s.strides, self.s.sizes, strict=True)])

    def _proposals(self, logit: Tensor, delta: Tensor, anchors: Tensor, counts: list[int],
                   image_hw: tuple[int, int]) -> list[Tensor]:
        out = []
        for i in range(logit.shape[0]):
            boxes, scores, levels, start = [], [], [], 0
            pre, post = ((self.s.pre_nms_train, self.s.post_nms_train) if self.training
                         else (self.s.pre_nms_test, self.s.post_nms_test))
            for lvl, n in enumerate(counts):
                sc = logit[i, start:start + n]
                top = sc.topk(min(pre, n)).indices + start
                b = clip_boxes(decode_boxes(delta[i, top], anchors[top]), *image_hw)
                boxes.append(b)
                scores.append(logit[i, top])
                levels.append(torch.full((len(top),), lvl, device=b.device))
                start += n
            b, sc, lv = torch.cat(boxes), torch.cat(scores), torch.cat(levels)
            ok = ((b[:, 2] - b[:, 0]) >= self.s.min_size) & ((b[:, 3] - b[:, 1]) >= self.s.min_size)
            b, sc, lv = b[ok], sc[ok], lv[ok]
            keep = batched_nms(b, sc, lv, self.s.nms_thresh, max_keep=post)
            out.append(b[keep])
        return out

    def _losses(self, logit: Tensor, delta: Tensor, anchors: Tensor, gt_boxes: list[Tensor]) -> dict[str, Tensor]:
        sampled_pos, sampled_neg, targets = [], [], []
        for i, gt in enumerate(gt_boxes):
            m = match(box_iou(gt, anchors), self.s.fg_iou, self.s.bg_iou, allow_low_quality=True)
            pos, neg = sample(m >= 0, m == BELOW, self.s.batch_per_image, self.s.pos_fraction)
            sampled_pos.append(pos + i * anchors.shape[0])
            sampled_neg.append(neg + i * anchors.shape[0])
            targets.append(encode_boxes(gt[m[pos]], anchors[pos]) if len(pos) else delta.new_zeros(0, 4))
        pos, neg = torch.cat(sampled_pos), torch.cat(sampled_neg)
        flat_logit, flat_delta = logit.reshape(-1), delta.reshape(-1, 4)
        n = max(pos.numel() + neg.numel(), 1)
        idx = torch.cat([pos, neg])
        labels = torch.cat([torch.ones_like(pos), torch.zeros_like(neg)]).to(flat_logit.dtype)
        obj = F.binary_cross_entropy_with_logits(flat_logit[idx], labels, reduction="sum") / n
        box = F.smooth_l1_loss(flat_delta[pos], torch.cat(targets), beta=1 / 9, reduction="sum") / n
        return {"rpn_objectness": obj, "rpn_box": box}

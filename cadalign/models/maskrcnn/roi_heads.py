"""Per-RoI heads: multi-scale RoIAlign, box/class head, mask head, RoI sampling, losses and post-processing.

Box regression uses torchvision's weights (10, 10, 5, 5); masks are ``M x M`` logits per class, trained
against the ground-truth mask RoI-aligned into the RoI (aligned=True, the same sampling as the features).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cadalign.models.maskrcnn.rpn import BELOW, match, sample
from cadalign.models.ops import batched_nms, box_iou, clip_boxes, decode_boxes, encode_boxes, roi_align

BOX_WEIGHTS = (10.0, 10.0, 5.0, 5.0)
"""Box-delta weights of the second stage (torchvision's)."""


def rois_with_batch(boxes: list[Tensor]) -> Tensor:
    """``(R, 5)`` rows ``(image index, x1, y1, x2, y2)`` from per-image ``(Ri, 4)`` boxes."""
    idx = [torch.full((len(b), 1), i, dtype=b.dtype, device=b.device) for i, b in enumerate(boxes)]
    return torch.cat([torch.cat(idx), torch.cat(boxes)], 1) if boxes else torch.zeros(0, 5)


class MultiScaleRoIAlign(nn.Module):
    """RoIAlign from the FPN level that suits each box: ``k = floor(4 + log2(sqrt(wh) / 224))`` in [2, 5]."""

    def __init__(self, output_size: int, sampling_ratio: int, strides: tuple[int, ...] = (4, 8, 16, 32)) -> None:
        super().__init__()
        self.output_size, self.sampling_ratio, self.strides = output_size, sampling_ratio, strides

    def forward(self, feats: list[Tensor], rois: Tensor) -> Tensor:
        c = feats[0].shape[1]
        out = feats[0].new_zeros(rois.shape[0], c, self.output_size, self.output_size)
        if rois.shape[0] == 0:
            return out
        scale = torch.sqrt(((rois[:, 3] - rois[:, 1]) * (rois[:, 4] - rois[:, 2])).clamp_min(1e-6))
        lvl = torch.floor(4 + torch.log2(scale / 224) + 1e-6).clamp(2, 1 + len(self.strides)).long() - 2
        for i, stride in enumerate(self.strides):
            sel = torch.nonzero(lvl == i).squeeze(1)
            if sel.numel():
                out[sel] = roi_align(feats[i], rois[sel], self.output_size, 1.0 / stride, self.sampling_ratio, True)
        return out


def context_windows(rois: Tensor, scale: float, min_px: float) -> tuple[Tensor, Tensor]:
    """Pooling windows around ``(R, 5)`` RoI rows: the same centre, each side ``max(scale * side, min_px)``.

    Returns the windows ``(R, 5)`` and ``(R, 2)`` the log ratios ``log(box side / window side)`` (x, y; <= 0
    when ``scale >= 1``), which tell the head where the box lies in the window it sees. Windows may extend
    past the image: RoIAlign reads zeros there.
    """
    b = rois[:, 1:]
    c = (b[:, :2] + b[:, 2:]) / 2
    side = (b[:, 2:] - b[:, :2]).clamp_min(1e-3)
    win = torch.maximum(side * scale, side.new_tensor(min_px))
    out = torch.cat([rois[:, :1], c - win / 2, c + win / 2], 1)
    return out, torch.log(side / win)


class BoxHead(nn.Module):
    """Two FC layers, then class logits ``(R, C)`` and class-specific deltas ``(R, 4C)``.

    With ``extra`` > 0, that many numbers per RoI (e.g. the box's place in a context window, see
    :func:`context_windows`) join the pooled features at the first layer."""

    def __init__(self, channels: int, pool: int, rep: int, num_classes: int, extra: int = 0) -> None:
        super().__init__()
        self.fc1 = nn.Linear(channels * pool * pool + extra, rep)
        self.fc2 = nn.Linear(rep, rep)
        self.cls = nn.Linear(rep, num_classes)
        self.box = nn.Linear(rep, 4 * num_classes)
        nn.init.normal_(self.cls.weight, std=0.01)
        nn.init.normal_(self.box.weight, std=0.001)
        for m in (self.cls, self.box):
            nn.init.zeros_(m.bias)

    def forward(self, x: Tensor, extra: Tensor | None = None) -> tuple[Tensor, Tensor]:
        x = x.flatten(1)
        if extra is not None:
            x = torch.cat([x, extra.to(x.dtype)], 1)
        x = F.relu(self.fc2(F.relu(self.fc1(x))))
        return self.cls(x), self.box(x)


class MaskHead(nn.Module):
    """Four 3x3 convs, a 2x transposed conv and per-class 1x1 logits: ``(R, C, 2P, 2P)``."""

    def __init__(self, channels: int, width: int, num_classes: int) -> None:
        super().__init__()
        layers, cin = [], channels
        for _ in range(4):
            layers += [nn.Conv2d(cin, width, 3, padding=1), nn.ReLU(inplace=True)]
            cin = width
        self.convs = nn.Sequential(*layers)
        self.up = nn.ConvTranspose2d(width, width, 2, 2)
        self.logits = nn.Conv2d(width, num_classes, 1)
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                nn.init.zeros_(m.bias)

    def forward(self, x: Tensor) -> Tensor:
        return self.logits(F.relu(self.up(self.convs(x))))


@dataclass
class SampledRoIs:
    """The RoIs a training step uses, per image concatenated.

    ``boxes`` (R, 4) proposals; ``image`` (R,) image index; ``labels`` (R,) class (0 = background);
    ``gt_index`` (R,) matched ground-truth index within its image (-1 for background).
    """

    boxes: Tensor
    image: Tensor
    labels: Tensor
    gt_index: Tensor
    weight: Tensor | None = None
    """(R,) weight of each RoI in the box head's losses (None = all 1): see :func:`instance_weights`."""

    def positive(self) -> SampledRoIs:
        keep = self.labels > 0
        return SampledRoIs(self.boxes[keep], self.image[keep], self.labels[keep], self.gt_index[keep],
                           None if self.weight is None else self.weight[keep])


def jitter_boxes(gt: Tensor, copies: int, sigma: float) -> Tensor:
    """``(copies * G, 4)`` randomly moved copies of ``(G, 4)`` boxes: centre shifts and log-size changes drawn
    from normal distributions with ``sigma`` times the box's side (resp. ``sigma``); torch's global generator."""
    if copies == 0 or gt.shape[0] == 0:
        return gt[:0]
    g = gt.repeat(copies, 1)
    side = (g[:, 2:] - g[:, :2]).clamp_min(1e-3)
    c = (g[:, :2] + g[:, 2:]) / 2 + sigma * side * torch.randn_like(side)
    half = side * torch.exp(sigma * torch.randn_like(side)) / 2
    return torch.cat([c - half, c + half], 1)


def sample_balanced(m: Tensor, is_neg: Tensor, batch: int, pos_fraction: float) -> tuple[Tensor, Tensor]:
    """As :func:`~cadalign.models.maskrcnn.rpn.sample`, but the positives are drawn round-robin over the
    ground-truth instances they match (``m`` >= 0 is a candidate's instance): every instance gets one before any
    gets a second, and so on, in random order within a round. Uniform draws favour parts with many matching
    proposals; a part of a few pixels has one or two candidates (its own box) and then often gets none."""

    def round_robin(pos: Tensor) -> Tensor:
        inst = m[pos]
        order = torch.argsort(inst, stable=True)
        pos, inst = pos[order], inst[order]
        counts = torch.bincount(inst)
        rank = torch.arange(pos.numel(), device=pos.device) - (torch.cumsum(counts, 0) - counts)[inst]
        tie = torch.randperm(counts.numel(), device=pos.device)[inst]  # random instance order within a round
        return pos[torch.argsort(rank * counts.numel() + tie)]

    return sample(m >= 0, is_neg, batch, pos_fraction, order=round_robin)


def instance_weights(gt_index: Tensor, labels: Tensor) -> Tensor:
    """Box-head loss weights that give every matched instance the same total: a positive RoI weighs
    ``P / (G * n_g)`` (``P`` positives over ``G`` instances, ``n_g`` of them on its instance), so the positives
    still weigh ``P`` in all; background RoIs weigh 1."""
    w = torch.ones(labels.shape[0], dtype=torch.float32, device=labels.device)
    pos = labels > 0
    if pos.any():
        _, inv, counts = torch.unique(gt_index[pos], return_inverse=True, return_counts=True)
        w[pos] = float(pos.sum()) / (counts.numel() * counts[inv].float())
    return w


def sample_rois(proposals: list[Tensor], targets: list[dict], batch: int, pos_fraction: float,
                iou_thresh: float = 0.5, jitter: int = 0, jitter_sigma: float = 0.1,
                balance: bool = False) -> SampledRoIs:
    """Match proposals (plus the ground-truth boxes) to the targets and sample a balanced set.

    With ``jitter`` > 0 that many randomly moved copies of each ground-truth box (:func:`jitter_boxes`) join
    the candidates: a part of a few pixels otherwise has almost no proposal at IoU >= 0.5 besides its exact box,
    while at inference the head scores proposals a pixel or two off. With ``balance`` the positives are drawn
    per instance (:func:`sample_balanced`) and weighted so that each instance counts the same in the box head's
    losses (:func:`instance_weights`, per image).
    """
    boxes, image, labels, gt_index, weight = [], [], [], [], []
    for i, (props, t) in enumerate(zip(proposals, targets, strict=True)):
        gt = t["boxes"]
        cand = torch.cat([props, gt, jitter_boxes(gt, jitter, jitter_sigma).to(props.dtype)])
        m = match(box_iou(gt, cand), iou_thresh, iou_thresh, allow_low_quality=False)
        if balance:
            pos, neg = sample_balanced(m, m == BELOW, batch, pos_fraction)
        else:
            pos, neg = sample(m >= 0, m == BELOW, batch, pos_fraction)
        idx = torch.cat([pos, neg])
        gi = torch.cat([m[pos], torch.full_like(neg, -1)])
        lab = torch.cat([t["labels"][m[pos]], torch.zeros_like(neg)])
        boxes.append(cand[idx])
        image.append(torch.full_like(idx, i))
        labels.append(lab)
        gt_index.append(gi)
        if balance:
            weight.append(instance_weights(gi, lab))
    return SampledRoIs(torch.cat(boxes), torch.cat(image), torch.cat(labels), torch.cat(gt_index),
                       torch.cat(weight) if balance else None)


def box_losses(logits: Tensor, deltas: Tensor, rois: SampledRoIs, targets: list[dict]) -> dict[str, Tensor]:
    """Cross-entropy over classes and smooth-L1 on the true class's deltas (normalised by all RoIs), each RoI
    weighted by ``rois.weight`` when it is set (the weights sum to the RoI count, so the scale is unchanged)."""
    if rois.weight is None:
        cls_loss = F.cross_entropy(logits, rois.labels)
    else:
        ce = F.cross_entropy(logits, rois.labels, reduction="none")
        cls_loss = (ce * rois.weight.to(ce.dtype)).sum() / max(rois.labels.numel(), 1)
    pos = torch.nonzero(rois.labels > 0).squeeze(1)
    if pos.numel() == 0:
        return {"roi_cls": cls_loss, "roi_box": deltas.sum() * 0}
    gt = torch.stack([targets[int(i)]["boxes"][int(g)] for i, g in zip(rois.image[pos], rois.gt_index[pos],
                                                                        strict=True)])
    target = encode_boxes(gt, rois.boxes[pos], BOX_WEIGHTS)
    lab = rois.labels[pos]
    pred = deltas.view(deltas.shape[0], -1, 4)[pos, lab]
    if rois.weight is None:
        box_loss = F.smooth_l1_loss(pred, target, beta=1 / 9, reduction="sum") / max(rois.labels.numel(), 1)
    else:
        per = F.smooth_l1_loss(pred, target, beta=1 / 9, reduction="none").sum(1) * rois.weight[pos].to(pred.dtype)
        box_loss = per.sum() / max(rois.labels.numel(), 1)
    return {"roi_cls": cls_loss, "roi_box": box_loss}


def mask_targets(rois: SampledRoIs, targets: list[dict], size: int) -> Tensor:
    """``(P, size, size)`` binary targets: each positive RoI's matched GT mask resampled into the RoI."""
    out = []
    for i, t in enumerate(targets):
        sel = torch.nonzero(rois.image == i).squeeze(1)
        if sel.numel() == 0:
            continue
        masks = t["masks"][:, None].to(rois.boxes.dtype)
        r = torch.cat([rois.gt_index[sel, None].to(rois.boxes.dtype), rois.boxes[sel]], 1)
        out.append((sel, roi_align(masks, r, size, 1.0, 2, True)[:, 0]))
    res = rois.boxes.new_zeros(rois.boxes.shape[0], size, size)
    for sel, m in out:
        res[sel] = m
    return (res >= 0.5).to(res.dtype)


def mask_loss(mask_logits: Tensor, rois: SampledRoIs, targets: list[dict]) -> Tensor:
    """Per-pixel BCE of the true class's mask logits against :func:`mask_targets`."""
    if rois.labels.numel() == 0:
        return mask_logits.sum() * 0
    sel = mask_logits[torch.arange(len(rois.labels)), rois.labels]
    return F.binary_cross_entropy_with_logits(sel, mask_targets(rois, targets, sel.shape[-1]))


def postprocess(logits: Tensor, deltas: Tensor, boxes: list[Tensor], image_hw: tuple[int, int],
                score_thresh: float, nms_thresh: float, max_dets: int) -> list[tuple[Tensor, Tensor, Tensor]]:
    """Per image: final boxes ``(D, 4)``, scores ``(D,)``, labels ``(D,)`` (class-wise NMS, best first)."""
    scores = F.softmax(logits, -1)
    n_cls = scores.shape[1]
    all_boxes = torch.cat(boxes) if boxes else deltas.new_zeros(0, 4)
    pred = clip_boxes(decode_boxes(deltas, all_boxes, BOX_WEIGHTS).view(-1, n_cls, 4), *image_hw)
    out, start = [], 0
    for b in boxes:
        n = b.shape[0]
        bx, sc = pred[start:start + n, 1:].reshape(-1, 4), scores[start:start + n, 1:].reshape(-1)
        lab = torch.arange(1, n_cls, device=sc.device).repeat(n)
        ok = (sc > score_thresh) & ((bx[:, 2] - bx[:, 0]) >= 1e-2) & ((bx[:, 3] - bx[:, 1]) >= 1e-2)
        bx, sc, lab = bx[ok], sc[ok], lab[ok]
        keep = batched_nms(bx, sc, lab, nms_thresh, max_keep=max_dets)
        out.append((bx[keep], sc[keep], lab[keep]))
        start += n
    return out


def paste_masks(probs: Tensor, boxes: Tensor, image_hw: tuple[int, int], thresh: float = 0.5) -> Tensor:
    """Paste ``(D, M, M)`` RoI mask probabilities into ``(D, H, W)`` bool image masks.

    Image pixel ``(x, y)`` (centre ``x + .5``) samples the RoI mask at ``((x + .5 - x1) / w) M`` with bilinear
    interpolation (mask pixel centres at ``x1 + (j + .5) w / M``), the inverse of the RoIAlign targets.
    """
    h, w = image_hw
    out = torch.zeros(probs.shape[0], h, w, dtype=torch.bool, device=probs.device)
    for d in range(probs.shape[0]):
        x1, y1, x2, y2 = boxes[d].tolist()
        c0, c1 = max(int(math.floor(x1)), 0), min(int(math.ceil(x2)), w)
        r0, r1 = max(int(math.floor(y1)), 0), min(int(math.ceil(y2)), h)
        if c1 <= c0 or r1 <= r0:
            continue
        xs = (torch.arange(c0, c1, device=probs.device) + 0.5 - x1) / max(x2 - x1, 1e-6) * 2 - 1
        ys = (torch.arange(r0, r1, device=probs.device) + 0.5 - y1) / max(y2 - y1, 1e-6) * 2 - 1
        gy, gx = torch.meshgrid(ys, xs, indexing="ij")
        grid = torch.stack([gx, gy], -1)[None].to(probs.dtype)
        val = F.grid_sample(probs[d][None, None], grid, mode="bilinear", align_corners=False, padding_mode="border")
        out[d, r0:r1, c0:c1] = val[0, 0] >= thresh
    return out

"""Mask R-CNN (He et al. 2017) with a per-RoI 6-DoF pose head, in pure torch.

``MaskRCNNPose(cfg, classes)``: ResNet + FPN -> RPN -> box/class head, mask head and pose head on
RoIAlign features. In training mode ``forward(images, targets, pose_loss=...)`` returns the losses; in
eval mode it returns per-image detections at the resolution of ``images``. :meth:`MaskRCNNPose.detect` is
the inference entry point: one image of any size and its ``K``; it resizes to ``cfg.input_hw`` (scaling K),
and returns :class:`Detection`s in the input image's pixels with poses in metres.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from cadalign.config import bounded, from_dict, to_dict
from cadalign.errors import TrainingError
from cadalign.models.maskrcnn.backbone import STRIDES, BackboneFPN
from cadalign.models.maskrcnn.pose_head import PoseHead, PoseParam, decode_pose
from cadalign.models.maskrcnn.roi_heads import (
    BoxHead,
    MaskHead,
    MultiScaleRoIAlign,
    SampledRoIs,
    box_losses,
    context_windows,
    mask_loss,
    paste_masks,
    postprocess,
    rois_with_batch,
    sample_rois,
)
from cadalign.models.maskrcnn.rpn import RPN, RPNSettings
from cadalign.types import Detection

MODEL_KIND = "maskrcnn_pose"
"""``extra_state["model"]`` of checkpoints written by ``cadalign train pose``."""

_MEAN = (0.485, 0.456, 0.406)
_STD = (0.229, 0.224, 0.225)


@dataclass(frozen=True)
class MaskRCNNConfig:
    depth: int = 18
    """ResNet depth: 18, 34 or 50."""
    width: int = bounded(64, ge=4)
    """ResNet stem/first-stage width (64 = standard; smaller for fast tests)."""
    fpn_channels: int = bounded(256, ge=4)
    """Channels of every pyramid level and of the RPN head."""
    input_hw: tuple[int, int] = (480, 640)
    """(height, width) the network sees; ``detect`` resizes images to it and scales K."""
    anchor_sizes: tuple[float, ...] = (32.0, 64.0, 128.0, 256.0, 512.0)
    """Anchor side (px at ``input_hw``) on P2..P6."""
    anchor_ratios: tuple[float, ...] = (0.5, 1.0, 2.0)
    """Anchor aspect ratios h / w."""
    anchor_scales: tuple[float, ...] = (1.0,)
    """Multipliers of each level's anchor size, e.g. ``(1, 2^(1/3), 2^(2/3))`` (RetinaNet's three scales per
    octave): parts of 5-20 px fall between one-size levels and match no anchor at the RPN's IoU."""
    rpn_fg_iou: float = bounded(0.7, gt=0, le=1)
    """Anchors overlapping a ground-truth box at least this much are RPN positives (each box also claims its
    best anchor). 0.7 is for COCO-sized objects; a stride-4 grid gives a 10 px part no anchor that close."""
    rpn_bg_iou: float = bounded(0.3, ge=0, le=1)
    """Anchors overlapping every ground-truth box less than this are RPN negatives."""
    rpn_pre_nms_train: int = bounded(2000, ge=1)
    """Top-scoring anchors per level kept before NMS (training)."""
    rpn_post_nms_train: int = bounded(1000, ge=1)
    """Proposals per image after NMS (training)."""
    rpn_pre_nms_test: int = bounded(1000, ge=1)
    """Top-scoring anchors per level kept before NMS (inference)."""
    rpn_post_nms_test: int = bounded(1000, ge=1)
    """Proposals per image after NMS (inference)."""
    rpn_batch_per_image: int = bounded(256, ge=1)
    """Anchors sampled per image for the RPN loss."""
    roi_batch_per_image: int = bounded(512, ge=1)
    """RoIs sampled per image for the second-stage losses."""
    roi_pos_fraction: float = bounded(0.25, gt=0, le=1)
    """Largest fraction of positive RoIs in a sample."""
    roi_jitter: int = bounded(0, ge=0)
    """Randomly moved copies of each ground-truth box added to the training RoI candidates (0 = only the box itself, as
    Mask R-CNN), so small parts' heads train on RoIs as far off as their proposals. 0: neutral on the default orbit
    (docs/tuning/train_config.md#maskrcnnconfigroi_jitter)."""
    roi_jitter_sigma: float = bounded(0.1, ge=0)
    """Spread of those copies: centre shift and log-size change, as a fraction of the box's side."""
    roi_balance: bool = False
    """Draw the second stage's positive RoIs round-robin over the ground-truth instances and weight the box head's
    losses so each instance counts the same (:func:`~cadalign.models.maskrcnn.roi_heads.sample_rois`), not starving
    the smallest parts. Mixed across seeds (docs/tuning/train_config.md#maskrcnnconfigroi_balance)."""
    box_context: float = bounded(1.0, ge=1)
    """The box head pools a window this many times each proposal's side (same centre; see ``box_context_px``), so a part
    of a few pixels is seen with its surroundings; 1 = the proposal itself, as Mask R-CNN, since more context measured
    worse (docs/tuning/train_config.md#maskrcnnconfigbox_context)."""
    box_context_px: float = bounded(0.0, ge=0)
    """Smallest side (px at ``input_hw``) of the box head's pooling window. When a window differs from its
    proposal, the head also gets ``log(proposal side / window side)`` per axis, so it knows where the proposal
    lies (its deltas stay relative to the proposal)."""
    box_rep: int = bounded(1024, ge=4)
    """Width of the box head's two FC layers."""
    mask_channels: int = bounded(256, ge=4)
    """Width of the mask head's convs."""
    pose_channels: int = bounded(256, ge=4)
    """Width of the pose head's convs."""
    pose_rep: int = bounded(512, ge=4)
    """Width of the pose head's FC layers."""
    sampling_ratio: int = 2
    """RoIAlign samples per bin per axis (<= 0: adaptive)."""
    pose: PoseParam = "improved"
    """Pose parameterisation: ``thesis`` (Euler + t, L1) or ``improved`` (allocentric 6D + scale-invariant t)."""
    box_nms_thresh: float = bounded(0.5, ge=0, le=1)
    """Class-wise NMS IoU threshold of the final detections."""
    detections_per_image: int = bounded(100, ge=1)
    """Most detections returned per image."""

    def __post_init__(self) -> None:
        if self.depth not in (18, 34, 50):
            raise ValueError(f"depth must be 18, 34 or 50, got {self.depth}")
        if len(self.anchor_sizes) != len(STRIDES):
            raise ValueError(f"anchor_sizes needs {len(STRIDES)} values (P2..P6), got {len(self.anchor_sizes)}")
        if self.rpn_bg_iou > self.rpn_fg_iou:
            raise ValueError(f"rpn_bg_iou {self.rpn_bg_iou} must not exceed rpn_fg_iou {self.rpn_fg_iou}")
        if not self.anchor_scales or min(self.anchor_scales) <= 0:
            raise ValueError(f"anchor_scales must be positive multipliers, got {self.anchor_scales}")
        if min(self.input_hw) < 32:
            raise ValueError(f"input_hw must be at least 32 x 32, got {self.input_hw}")


@dataclass
class PoseRoIs:
    """Raw pose outputs of the positive training RoIs with their matched targets (for the pose loss).

    ``raw`` (P, D) of the true class; ``boxes`` (P, 4) RoI px; ``labels``/``obj_ids`` (P,); ``R`` (P, 3, 3),
    ``t`` (P, 3) m ground truth; ``K`` (P, 3, 3) of the image the network saw; ``param`` the parameterisation.
    """

    raw: Tensor
    boxes: Tensor
    labels: Tensor
    obj_ids: Tensor
    R: Tensor
    t: Tensor
    K: Tensor
    param: str


class MaskRCNNPose(nn.Module):
    """Mask R-CNN + pose head. ``classes[0]`` is the background."""

    def __init__(self, cfg: MaskRCNNConfig, classes: Sequence[str]) -> None:
        super().__init__()
        if len(classes) < 2:
            raise ValueError(f"need the background and at least one class, got {list(classes)}")
        self.cfg, self.classes = cfg, tuple(classes)
        n = len(classes)
        self.backbone = BackboneFPN(cfg.depth, cfg.width, cfg.fpn_channels)
        c = cfg.fpn_channels
        self.rpn = RPN(c, RPNSettings(tuple(cfg.anchor_sizes), tuple(cfg.anchor_ratios), STRIDES,
                                      cfg.rpn_pre_nms_train, cfg.rpn_post_nms_train, cfg.rpn_pre_nms_test,
                                      cfg.rpn_post_nms_test, fg_iou=cfg.rpn_fg_iou, bg_iou=cfg.rpn_bg_iou,
                                      batch_per_image=cfg.rpn_batch_per_image, scales=tuple(cfg.anchor_scales)))
        self.box_pool = MultiScaleRoIAlign(7, cfg.sampling_ratio)
        self.mask_pool = MultiScaleRoIAlign(14, cfg.sampling_ratio)
        self.box_head = BoxHead(c, 7, cfg.box_rep, n, 2 if self._context else 0)
        self.mask_head = MaskHead(c, cfg.mask_channels, n)
        self.pose_head = PoseHead(c, 14, cfg.pose_channels, cfg.pose_rep, n, cfg.pose)
        self.register_buffer("mean", torch.tensor(_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(_STD).view(1, 3, 1, 1), persistent=False)
        self.last_timings: dict[str, float] = {}
        """Seconds per stage of the last ``inference``/``detect`` call: detector, mask, pose."""

    def _features(self, images: Tensor) -> list[Tensor]:
        if images.dim() != 4 or images.shape[1] != 3:
            raise ValueError(f"images must be (N, 3, H, W) in [0, 1], got {tuple(images.shape)}")
        pyr = self.backbone((images - self.mean) / self.std)
        return list(pyr.values())

    def forward(self, images: Tensor, targets: list[dict] | None = None,
                pose_loss: Callable[[PoseRoIs], dict[str, Tensor]] | None = None) -> dict[str, Tensor] | list[dict]:
        """Training (``self.training``): losses; else per-image dicts (see :meth:`inference`).

        Targets per image: ``boxes`` (G, 4) px, ``labels`` (G,), ``masks`` (G, H, W) bool, and for the pose
        loss ``R`` (G, 3, 3), ``t`` (G, 3) m, ``K`` (3, 3), ``obj_ids`` (G,).
        """
        if not self.training:
            return self.inference(images)
        if targets is None:
            raise ValueError("training mode needs targets (or call model.eval())")
        feats = self._features(images)
        hw = (images.shape[-2], images.shape[-1])
        proposals, losses = self.rpn(feats, hw, [t["boxes"] for t in targets])
        rois = sample_rois(proposals, targets, self.cfg.roi_batch_per_image, self.cfg.roi_pos_fraction,
                           jitter=self.cfg.roi_jitter, jitter_sigma=self.cfg.roi_jitter_sigma,
                           balance=self.cfg.roi_balance)
        logits, deltas = self._box_logits(feats, self._rois(rois))
        losses.update(box_losses(logits, deltas, rois, targets))
        pos = rois.positive()
        pooled = self.mask_pool(feats[:4], self._rois(pos))
        losses["mask"] = mask_loss(self.mask_head(pooled), pos, targets)
        if pose_loss is not None:
            Ks = torch.stack([t["K"] for t in targets]).to(pos.boxes)[pos.image]
            raw = self.pose_head(pooled, pos.boxes, Ks)[torch.arange(len(pos.labels)), pos.labels]
            losses.update(pose_loss(self._pose_rois(raw, pos, targets)))
        return losses

    def _box_stage(self, images: Tensor) -> tuple[list[Tensor], list[Tensor], Tensor, Tensor]:
        """Inference up to the box head: pyramid features, proposals per image, class logits and deltas."""
        feats = self._features(images)
        proposals, _ = self.rpn(feats, (images.shape[-2], images.shape[-1]))
        logits, deltas = self._box_logits(feats, rois_with_batch(proposals))
        return feats, proposals, logits, deltas

    @property
    def _context(self) -> bool:
        return self.cfg.box_context != 1.0 or self.cfg.box_context_px > 0

    def _box_logits(self, feats: list[Tensor], rois: Tensor) -> tuple[Tensor, Tensor]:
        """Class logits and deltas of ``(R, 5)`` RoI rows (pooled in their context window when configured)."""
        if not self._context:
            return self.box_head(self.box_pool(feats[:4], rois))
        windows, where = context_windows(rois, self.cfg.box_context, self.cfg.box_context_px)
        return self.box_head(self.box_pool(feats[:4], windows), where)

    @staticmethod
    def _rois(rois: SampledRoIs) -> Tensor:
        return torch.cat([rois.image[:, None].to(rois.boxes.dtype), rois.boxes], 1)

    def _pose_rois(self, raw: Tensor, pos: SampledRoIs, targets: list[dict]) -> PoseRoIs:
        def pick(key: str) -> Tensor:
            rows = [targets[int(i)][key][int(g)] for i, g in zip(pos.image, pos.gt_index, strict=True)]
            return torch.stack(rows) if rows else targets[0][key][:0]

        Ks = [targets[int(i)]["K"] for i in pos.image]
        K = torch.stack(Ks) if Ks else raw.new_zeros(0, 3, 3)
        return PoseRoIs(raw, pos.boxes, pos.labels, pick("obj_ids"), pick("R"), pick("t"), K, self.cfg.pose)

    @torch.no_grad()
    def inference(self, images: Tensor, score_thresh: float = 0.05, paste: bool = True,
                  K: Tensor | None = None) -> list[dict]:
        """Per image: ``boxes`` (D, 4) px, ``scores``, ``labels``, ``mask_probs`` (D, 28, 28) of the RoI,
        ``masks`` (D, H, W) bool (when ``paste``), ``pose_raw`` (D, dims) of the predicted class — at the size
        of ``images``. ``K`` (N, 3, 3) are the intrinsics of ``images`` (the pose head sees the RoIs in
        normalised camera coordinates); None stands for ``fx = W, fy = H`` and the principal point at the image
        centre. Seconds per stage (detector, mask, pose) are left in ``self.last_timings``."""
        t0 = time.perf_counter()
        hw = (images.shape[-2], images.shape[-1])
        feats, proposals, logits, deltas = self._box_stage(images)
        dets = postprocess(logits, deltas, proposals, hw, score_thresh, self.cfg.box_nms_thresh,
                           self.cfg.detections_per_image)
        boxes = [b for b, _, _ in dets]
        pooled = self.mask_pool(feats[:4], rois_with_batch(boxes))
        labels = torch.cat([lab for _, _, lab in dets]) if dets else torch.zeros(0, dtype=torch.int64)
        rows = torch.arange(len(labels))
        t1 = time.perf_counter()
        probs = torch.sigmoid(self.mask_head(pooled))[rows, labels]
        t2 = time.perf_counter()
        if K is None:
            h, w = hw
            K = images.new_tensor([[w, 0.0, w / 2], [0.0, h, h / 2], [0.0, 0.0, 1.0]]).expand(len(images), 3, 3)
        K_rois = torch.cat([K[i].to(images).expand(len(b), 3, 3) for i, b in enumerate(boxes)])
        pose = self.pose_head(pooled, torch.cat(boxes), K_rois)[rows, labels]
        t3 = time.perf_counter()
        out, start = [], 0
        for b, s, lab in dets:
            sl = slice(start, start + len(b))
            masks = paste_masks(probs[sl], b, hw) if paste else None
            out.append({"boxes": b, "scores": s, "labels": lab, "mask_probs": probs[sl], "masks": masks,
                        "pose_raw": pose[sl]})
            start += len(b)
        self.last_timings = {"detector": t1 - t0, "mask": t2 - t1 + time.perf_counter() - t3, "pose": t3 - t2}
        return out

    def _net_input(self, image: Tensor) -> Tensor:
        """``(1, 3, h, w)`` float32 on the model's device: ``image`` (3, H, W) resized to ``cfg.input_hw``."""
        x = image.to(self.mean.device, torch.float32)[None]
        if tuple(image.shape[-2:]) != tuple(self.cfg.input_hw):
            x = F.interpolate(x, size=tuple(self.cfg.input_hw), mode="bilinear", align_corners=False, antialias=True)
        return x

    @torch.no_grad()
    def stage_boxes(self, image: Tensor) -> dict[str, Tensor]:
        """The first stages' boxes on one image, to tell where a part is lost (see
        :func:`cadalign.train.pose_eval.stage_recall`).

        Args:
            image: (3, H, W) float in [0, 1], any size (resized to ``cfg.input_hw`` as :meth:`detect` does).

        Returns:
            ``anchors`` (A, 4) of every pyramid level, ``proposals`` (P, 4) the RPN keeps at inference and
            ``proposal_probs`` (P, C) the box head's class probabilities of each, boxes in ``image`` pixels.
        """
        was_training = self.training
        self.eval()
        x = self._net_input(image)
        (h0, w0), (h, w) = image.shape[-2:], self.cfg.input_hw
        feats, proposals, logits, _ = self._box_stage(x)
        anchors = self.rpn.anchors(feats)
        self.train(was_training)
        back = torch.tensor([w0 / w, h0 / h, w0 / w, h0 / h], device=x.device)
        return {"anchors": anchors * back, "proposals": proposals[0] * back,
                "proposal_probs": torch.softmax(logits.float(), -1)}

    @torch.no_grad()
    def detect(self, image: Tensor, K: Tensor, score_thresh: float = 0.5) -> list[Detection]:
        """Detections with masks and poses on one image.

        Args:
            image: (3, H, W) float in [0, 1], any size (resized to ``cfg.input_hw``).
            K: (3, 3) intrinsics of ``image`` (pixel centres at integer + 0.5).
            score_thresh: smallest score returned.

        Returns:
            detections by decreasing score; boxes and masks in ``image`` pixels, poses in metres.
        """
        if image.dim() != 3 or image.shape[0] != 3 or tuple(K.shape) != (3, 3):
            raise ValueError(f"detect expects image (3, H, W) and K (3, 3), got {tuple(image.shape)}, {tuple(K.shape)}")
        t_start = time.perf_counter()
        was_training = self.training
        self.eval()
        dev = self.mean.device
        h0, w0 = image.shape[-2:]
        h, w = self.cfg.input_hw
        x = self._net_input(image)
        scale = torch.tensor([w / w0, h / h0, 1.0], dtype=torch.float32, device=dev)
        K_net = scale[:, None] * K.to(dev, torch.float32)
        t0 = time.perf_counter()
        res = self.inference(x, score_thresh=score_thresh, paste=False, K=K_net[None])[0]
        timings = dict(self.last_timings)
        timings["detector"] += t0 - t_start  # the resize
        n = len(res["boxes"])
        t1 = time.perf_counter()
        R, t = decode_pose(res["pose_raw"], self.cfg.pose, K_net.expand(n, 3, 3), res["boxes"])
        t2 = time.perf_counter()
        boxes0 = res["boxes"] / torch.tensor([w / w0, h / h0, w / w0, h / h0], device=dev)
        masks = paste_masks(res["mask_probs"], boxes0, (h0, w0))
        self.last_timings = {**timings, "pose": timings["pose"] + t2 - t1,
                             "mask": timings["mask"] + time.perf_counter() - t2}
        self.train(was_training)
        return [
            Detection(boxes0[i].cpu().numpy().astype(np.float64), int(res["labels"][i]), float(res["scores"][i]),
                      masks[i].cpu().numpy(), R[i].cpu().double().numpy(), t[i].cpu().double().numpy())
            for i in range(n)
        ]


def load_pose_model(run_dir: Path, device: str = "cpu") -> tuple[MaskRCNNPose, dict]:
    """The trained model of a ``cadalign train pose`` run folder and its ``extra_state`` (classes, config).

    Raises:
        TrainingError: no checkpoint, or a checkpoint of another kind of model.
    """
    path = Path(run_dir) / "checkpoints" / "last.pt"
    if not path.is_file():
        raise TrainingError(f"no trained model in {run_dir}: {path} is missing (run 'cadalign train pose' first)")
    try:  # weights_only=False: the loop's checkpoints also hold RNG states (numpy tuples)
        ck = torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # torch raises many types for corrupt files
        raise TrainingError(f"{path} is not a readable checkpoint ({exc}); delete it or retrain") from exc
    if not isinstance(ck, dict):
        raise TrainingError(f"{path} is not a cadalign training checkpoint; pass a 'cadalign train pose' run folder")
    extra = ck.get("extra_state") or {}
    if extra.get("model") != MODEL_KIND:
        raise TrainingError(
            f"{path} is not a detection+pose checkpoint (it holds model {extra.get('model', '<unknown>')!r}, "
            f"expected {MODEL_KIND!r}); pass a run folder written by 'cadalign train pose'"
        )
    cfg = from_dict(MaskRCNNConfig, extra["model_config"], source=str(path))
    model = MaskRCNNPose(cfg, extra["classes"])
    model.load_state_dict(ck["model"])
    model.to(device).eval()
    return model, {**extra, "model_config": to_dict(cfg), "step": int(ck.get("step", 0))}

"""Random training crops for the detection + pose network (pose-preserving).

Small parts (valves ~20 px, hot stabs ~6-12 px at 640x480) shrink to a few pixels when a whole frame is
resized to a fast 320x240 input, below what the stride-4 pyramid level and a 0.5 box-IoU match can resolve.
Training instead on crops of the full-resolution frame keeps every part at the scale the network sees at
inference (the network is fully convolutional, so it then runs on the whole frame) at the cost per step of
the small input.

A crop only moves the image origin: the camera centre and orientation stay, so ``R``, ``t`` are unchanged and
``K``'s principal point shifts by the crop offset. Boxes are recomputed from the cropped visible masks;
instances with no pixel left are dropped (partly cut ones stay, as at the image border; the pose loss leaves
out RoIs whose object origin is far outside them, see ``PoseLossConfig.max_center_offset``).

A *zoomed* crop (``zoom > 1``) cuts a window ``zoom`` times smaller than the crop and upsamples it to the crop
size: the same camera centre and orientation with focal length and principal point (measured from the
window's corner) multiplied by ``zoom`` (pixel-edge convention: pixel ``i`` covers ``[i, i + 1)``, as in
``F.interpolate(align_corners=False)``). A part then looks as it would ``zoom`` times closer, so a network
trained on far parts also sees them at the size of nearer ones. ``R``, ``t`` stay; masks are resampled
(bilinear, >= 0.5) and boxes recomputed from them; the ``improved`` head's translation codes follow from the
zoomed ``K`` (``dz = t_z s / f_x`` is unchanged, the box and ``f_x`` both scale).

A *rolled* frame (``rotate_prob``) is the frame the camera would have taken after turning by ``theta`` about
its optical axis: the image is warped by the homography ``K Rz(theta) K^-1`` (exact for any ``K``, as a pure
camera rotation is), masks likewise (see :func:`roll_frame`), boxes recomputed, ``R' = Rz R``, ``t' = Rz t`` (the
depth ``t_z`` is unchanged) and ``K`` stays. Thin parts then appear at image orientations the trajectory never
gave them. Pixels from outside the frame are black. The roll is applied to the whole frame, before the crop.

A *pasted* frame (``paste_prob``) first gets some instances of another frame of the batch copied in where they
were (same camera, so their poses hold exactly): parts are then seen on other backgrounds and rare classes
appear more often (see :func:`paste_instances`).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

_PER_IMAGE = ("boxes", "labels", "masks", "R", "t", "obj_ids")


def masks_to_boxes(masks: Tensor) -> Tensor:
    """``(G, 4)`` float xyxy boxes (exclusive max, pixel edges) of ``(G, H, W)`` bool masks; all have pixels."""
    if masks.shape[0] == 0:
        return torch.zeros(0, 4, device=masks.device)
    rows, cols = masks.any(2), masks.any(1)
    h, w = masks.shape[-2:]
    ar_h = torch.arange(h, device=masks.device)
    ar_w = torch.arange(w, device=masks.device)
    y0 = torch.where(rows, ar_h, h).min(1).values
    y1 = torch.where(rows, ar_h, -1).max(1).values + 1
    x0 = torch.where(cols, ar_w, w).min(1).values
    x1 = torch.where(cols, ar_w, -1).max(1).values + 1
    return torch.stack([x0, y0, x1, y1], 1).float()


def crop_origin(hw: tuple[int, int], crop_hw: tuple[int, int], boxes: Tensor, g: torch.Generator,
                object_prob: float, labels: Tensor | None = None) -> tuple[int, int]:
    """Top-left ``(y0, x0)`` of a crop: with ``object_prob`` one holding a random instance's box centre, else uniform.

    Instances are drawn uniformly, so the many small parts are in most crops, not only the large structure.
    With ``labels`` (G,) the draw is balanced by class instead: a class present in the image uniformly, then
    one of its instances, so a class with few instances per frame is centred as often as a frequent one. Both
    draws use the same random numbers (the stream does not change).
    """
    h, w = hw
    ch, cw = crop_hw
    u = torch.rand(4, generator=g, device=g.device).tolist()
    if len(boxes) and u[0] < object_prob:
        b = boxes[pick_instance(u[1], len(boxes), labels)]
        cx, cy = float(b[0] + b[2]) / 2, float(b[1] + b[3]) / 2
        # the centre lands uniformly inside the crop, then the crop is clamped into the image
        x0, y0 = cx - u[2] * cw, cy - u[3] * ch
    else:
        x0, y0 = u[2] * (w - cw), u[3] * (h - ch)
    return int(round(min(max(y0, 0.0), h - ch))), int(round(min(max(x0, 0.0), w - cw)))


def pick_instance(u: float, n: int, labels: Tensor | None = None) -> int:
    """Instance index for a uniform draw ``u`` in ``[0, 1)``: uniform over the ``n`` instances, or with
    ``labels`` (n,) class-balanced (a class present uniformly, then one of its instances, from the same ``u``)."""
    pick = min(int(u * n), n - 1)
    if labels is not None:
        classes = torch.unique(labels)  # sorted
        c = min(int(u * len(classes)), len(classes) - 1)
        members = torch.nonzero(labels == classes[c]).squeeze(1)
        frac = u * len(classes) - c  # uniform in [0, 1) given the class
        pick = int(members[min(int(frac * len(members)), len(members) - 1)])
    return pick


def crop_target(target: dict, y0: int, x0: int, crop_hw: tuple[int, int]) -> dict:
    """One image's targets cropped to ``[y0, y0 + ch) x [x0, x0 + cw)``: masks, boxes, K; empty instances dropped."""
    ch, cw = crop_hw
    masks = target["masks"][:, y0:y0 + ch, x0:x0 + cw]
    keep = torch.nonzero(masks.flatten(1).any(1)).squeeze(1)
    out = {k: target[k][keep] for k in _PER_IMAGE if k != "masks"}
    out["masks"] = masks[keep]
    out["boxes"] = masks_to_boxes(out["masks"]).to(target["boxes"].dtype)
    K = target["K"].clone()
    K[0, 2] -= x0
    K[1, 2] -= y0
    out["K"] = K
    return out


def zoom_target(target: dict, out_hw: tuple[int, int]) -> dict:
    """One (cropped) image's targets upsampled to ``out_hw``: masks resampled, boxes recomputed, K scaled.

    The scale is ``out / in`` per axis; instances whose mask vanishes are dropped.
    """
    h, w = target["masks"].shape[-2:]
    oh, ow = out_hw
    if (h, w) == (oh, ow):
        return target
    masks = target["masks"]
    if len(masks):
        masks = F.interpolate(masks[:, None].float(), size=out_hw, mode="bilinear", align_corners=False)[:, 0] >= 0.5
    else:
        masks = torch.zeros(0, oh, ow, dtype=torch.bool, device=masks.device)
    keep = torch.nonzero(masks.flatten(1).any(1)).squeeze(1)
    out = {k: target[k][keep] for k in _PER_IMAGE if k != "masks"}
    out["masks"] = masks[keep]
    out["boxes"] = masks_to_boxes(out["masks"]).to(target["boxes"].dtype)
    scale = torch.tensor([ow / w, oh / h, 1.0], dtype=target["K"].dtype, device=target["K"].device)
    out["K"] = scale[:, None] * target["K"]
    return out


def draw_zoom(g: torch.Generator, prob: float, zoom_max: float) -> float:
    """A zoom factor: 1 with probability ``1 - prob``, else log-uniform in ``[1, zoom_max]``.

    Nothing is drawn when ``prob`` is 0, so recipes without zoom keep their random stream.
    """
    if prob <= 0 or zoom_max <= 1:
        return 1.0
    u = torch.rand(2, generator=g, device=g.device).tolist()
    return float(zoom_max ** u[1]) if u[0] < prob else 1.0


def roll_matrix(theta: float, dtype: torch.dtype = torch.float32, device: torch.device | None = None) -> Tensor:
    """``Rz(theta)`` (3, 3): the camera-frame rotation about the optical axis (x towards y for ``theta > 0``)."""
    c, s = math.cos(theta), math.sin(theta)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=dtype, device=device)


def roll_frame(image: Tensor, target: dict, theta: float) -> tuple[Tensor, dict]:
    """One image ``(3, H, W)`` and its targets as seen after the camera rolls by ``theta`` (radians).

    Output pixel centre ``p' = (x + .5, y + .5, 1)`` samples the input at ``K Rz^T K^-1 p'``; a camera point ``X``
    moves to ``Rz X``. ``K``'s last row is ``(0, 0, 1)``, so the map is affine. Disjoint (visible) masks are
    warped as one label map (nearest), overlapping ones one by one (bilinear, >= 0.5). Instances whose mask
    leaves the frame are dropped.
    """
    h, w = image.shape[-2:]
    K = target["K"].to(torch.float64)
    Rz = roll_matrix(theta, torch.float64, K.device)
    A = (K @ Rz.T @ torch.linalg.inv(K))[:2].to(image.dtype)  # output pixel -> input pixel, affine rows
    xs = torch.arange(w, dtype=image.dtype, device=image.device) + 0.5
    ys = torch.arange(h, dtype=image.dtype, device=image.device)[:, None] + 0.5
    u = A[0, 0] * xs + A[0, 1] * ys + A[0, 2]
    v = A[1, 0] * xs + A[1, 1] * ys + A[1, 2]
    grid = torch.stack([2 * u / w - 1, 2 * v / h - 1], -1)[None]  # align_corners=False
    warped = F.grid_sample(image[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0]
    masks, boxes = target["masks"], None
    g = len(masks)
    if g:
        flat = masks.reshape(g, -1).to(grid.dtype)
        if float(flat.sum(0).max()) <= 1:  # disjoint: one label map (0 = none, i + 1 = instance i)
            ids = torch.arange(1, g + 1, dtype=grid.dtype, device=masks.device)
            labels = (ids @ flat).reshape(1, 1, h, w)
            rolled = F.grid_sample(labels, grid, mode="nearest", padding_mode="zeros",
                                   align_corners=False).reshape(-1).round().long()
            masks = (rolled[None] == ids.long()[:, None]).reshape(g, h, w)
            boxes = _label_boxes(rolled, g, h, w)
        else:
            masks = F.grid_sample(masks[:, None].to(grid.dtype), grid.expand(g, -1, -1, -1), mode="bilinear",
                                  padding_mode="zeros", align_corners=False)[:, 0] >= 0.5
    if boxes is None:
        boxes = masks_to_boxes(masks) if g else torch.zeros(0, 4, device=masks.device)
    keep = torch.nonzero(boxes[:, 2] > boxes[:, 0]).squeeze(1)
    out = {k: target[k][keep] for k in _PER_IMAGE if k not in ("masks", "R", "t")}
    out["masks"] = masks[keep]
    out["boxes"] = boxes[keep].to(target["boxes"].dtype)
    Rz_t = Rz.to(target["R"].dtype)
    out["R"] = Rz_t @ target["R"][keep]
    out["t"] = target["t"][keep] @ Rz_t.T
    out["K"] = target["K"]
    return warped, out


def _label_boxes(labels: Tensor, g: int, h: int, w: int) -> Tensor:
    """``(g, 4)`` xyxy boxes (exclusive max) of the labels ``1..g`` of a flat ``(h * w,)`` label map, as
    :func:`masks_to_boxes` gives for the masks ``labels == i + 1``; an absent label gets ``(0, 0, 0, 0)``."""
    on = torch.nonzero(labels > 0).squeeze(1)
    lab = labels[on] - 1
    y, x = on // w, on % w
    lo = torch.full((2, g), max(h, w), dtype=torch.int64, device=labels.device)
    hi = torch.full((2, g), -1, dtype=torch.int64, device=labels.device)
    for row, c in enumerate((x, y)):
        lo[row].scatter_reduce_(0, lab, c, "amin")
        hi[row].scatter_reduce_(0, lab, c, "amax")
    present = hi[0] >= 0
    boxes = torch.stack([lo[0], lo[1], hi[0] + 1, hi[1] + 1], 1).float()
    return torch.where(present[:, None], boxes, torch.zeros_like(boxes))


def draw_roll(g: torch.Generator, prob: float, max_deg: float) -> float:
    """A roll angle (radians): 0 with probability ``1 - prob``, else uniform in ``[-max_deg, max_deg]`` degrees.

    Nothing is drawn when ``prob`` is 0, so recipes without rolls keep their random stream.
    """
    if prob <= 0 or max_deg <= 0:
        return 0.0
    u = torch.rand(2, generator=g, device=g.device).tolist()
    return math.radians((2 * u[1] - 1) * max_deg) if u[0] < prob else 0.0


def draw_paste(g: torch.Generator, prob: float, max_paste: int, donor: dict, image: Tensor,
               target: dict) -> list[int]:
    """Donor instances to paste (indices, in pasting order): none with probability ``1 - prob``, else
    ``max_paste`` class-balanced draws (see :func:`pick_instance`), repeats removed.

    Nothing is drawn when ``prob`` is 0, so recipes without pasting keep their random stream. Nothing is pasted
    when the donor's camera (``K``) or image size differs: the pasted pose would not hold.
    """
    if prob <= 0 or max_paste <= 0:
        return []
    u = torch.rand(1 + max_paste, generator=g, device=g.device).tolist()
    n = len(donor["labels"])
    if (u[0] >= prob or n == 0 or donor["masks"].shape[-2:] != image.shape[-2:]
            or not torch.allclose(donor["K"], target["K"])):
        return []
    picks: list[int] = []
    for v in u[1:]:
        i = pick_instance(v, n, donor["labels"])
        if i not in picks:
            picks.append(i)
    return picks


def paste_instances(image: Tensor, target: dict, donor_image: Tensor, donor: dict, picks: list[int],
                    min_visible: float = 0.1) -> tuple[Tensor, dict]:
    """``image`` with the visible pixels of the donor's instances ``picks`` pasted in place, and its targets.

    Both frames are taken by the same camera (same ``K`` and size): a donor instance keeps its pixel position,
    so its pose ``R``, ``t`` relative to the camera holds exactly in the new frame (simple copy-paste, Ghiasi
    et al. 2021, without moving or scaling the part). Later picks cover earlier ones. Every instance (the
    frame's own and the pasted) keeps the pixels nothing was pasted over; one left with fewer than
    ``min_visible`` of its pixels is dropped (its remnant is then background), as BOP leaves out targets under
    10 % visible. Boxes are recomputed from the masks.
    """
    if not picks:
        return image, target
    sel = torch.tensor(picks, dtype=torch.int64, device=donor["masks"].device)
    pasted = donor["masks"][sel]
    pasted_vis = pasted.clone()
    cover = torch.zeros_like(pasted[0])
    for i in range(len(picks) - 1, -1, -1):  # last pick on top: each keeps what the later ones leave
        pasted_vis[i] &= ~cover
        cover |= pasted[i]
    out_image = torch.where(cover[None], donor_image, image)
    masks = torch.cat([target["masks"] & ~cover, pasted_vis])
    before = torch.cat([target["masks"], pasted]).flatten(1).sum(1)
    after = masks.flatten(1).sum(1)
    keep = torch.nonzero((after > 0) & (after >= min_visible * before)).squeeze(1)
    out = {}
    for k in _PER_IMAGE:
        if k in ("masks", "boxes"):
            continue
        out[k] = torch.cat([target[k], donor[k][sel].to(target[k].dtype)])[keep]
    out["masks"] = masks[keep]
    out["boxes"] = masks_to_boxes(out["masks"]).to(target["boxes"].dtype)
    out["K"] = target["K"]
    return out_image, out


def crop_batch(batch: dict, g: torch.Generator, crop_hw: tuple[int, int], object_prob: float = 0.8,
               zoom_prob: float = 0.0, zoom_max: float = 2.0, balance_classes: bool = False,
               rotate_prob: float = 0.0, rotate_max_deg: float = 30.0, paste_prob: float = 0.0,
               paste_max: int = 3) -> dict:
    """A :func:`cadalign.train.datasets.detection_collate` batch with each image randomly cropped.

    ``image`` (B, 3, H, W) -> (B, 3, ch, cw); the per-image lists follow (see :func:`crop_target`). With
    probability ``zoom_prob`` an image's crop is instead a window ``z`` times smaller (``z`` log-uniform in
    ``[1, zoom_max]``) upsampled to ``crop_hw`` (see :func:`zoom_target`). ``balance_classes``: the instance a
    crop is placed around is drawn class-balanced (see :func:`crop_origin`). With probability ``rotate_prob``
    the frame is first rolled by up to ``rotate_max_deg`` (see :func:`roll_frame`). Before that, with probability
    ``paste_prob`` up to ``paste_max`` instances of the next image of the batch (class-balanced) are pasted into
    it where they are (see :func:`paste_instances`; a batch of one image pastes nothing).

    Raises:
        ValueError: the crop is larger than the images.
    """
    h, w = batch["image"].shape[-2:]
    ch, cw = crop_hw
    if ch > h or cw > w:
        raise ValueError(f"crop {crop_hw} is larger than the training images {(h, w)}; lower crop_hw")
    if (ch, cw) == (h, w) and zoom_prob <= 0 and rotate_prob <= 0 and paste_prob <= 0:
        return batch
    images, per = [], {k: [] for k in (*_PER_IMAGE, "K")}
    n = batch["image"].shape[0]
    for i in range(n):
        target = {k: batch[k][i] for k in (*_PER_IMAGE, "K")}
        frame = batch["image"][i]
        if paste_prob > 0 and n > 1:
            j = (i + 1) % n
            donor = {k: batch[k][j] for k in (*_PER_IMAGE, "K")}
            picks = draw_paste(g, paste_prob, paste_max, donor, frame, target)
            frame, target = paste_instances(frame, target, batch["image"][j], donor, picks)
        theta = draw_roll(g, rotate_prob, rotate_max_deg)
        if theta != 0.0:
            frame, target = roll_frame(frame, target, theta)
        z = draw_zoom(g, zoom_prob, zoom_max)
        src = (max(int(round(ch / z)), 1), max(int(round(cw / z)), 1))
        y0, x0 = crop_origin((h, w), src, target["boxes"], g, object_prob,
                             target["labels"] if balance_classes else None)
        image = frame[:, y0:y0 + src[0], x0:x0 + src[1]]
        cropped = crop_target(target, y0, x0, src)
        if src != (ch, cw):
            image = F.interpolate(image[None], size=(ch, cw), mode="bilinear", align_corners=False)[0]
            cropped = zoom_target(cropped, (ch, cw))
        images.append(image)
        for k, v in cropped.items():
            per[k].append(v)
    return {**batch, "image": torch.stack(images), **per}

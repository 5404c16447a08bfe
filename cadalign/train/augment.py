"""Seeded batch augmentations for dense tasks: colour and turbidity jitter, horizontal flips, crops.

Every random draw comes from the ``torch.Generator`` the training loop passes in (seeded per step), so a
resumed run augments exactly like an uninterrupted one. Geometric changes are applied to every dense target
in the batch: ``label`` (nearest), ``depth``/``valid`` (nearest) and an optional ``fg`` mask channel. A crop
of side fraction ``s`` resized back to full size magnifies the scene by ``1/s``, which for a fixed focal
length looks like the scene at ``s`` times the depth: depth targets are multiplied by ``s`` so the
image-to-depth relation stays that of the real camera.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import kornia.enhance as ke
import torch
import torch.nn.functional as F

from cadalign.config import bounded


@dataclass(frozen=True)
class AugmentConfig:
    enabled: bool = True
    """Apply augmentations at all."""
    hflip: float = bounded(0.5, ge=0, le=1)
    """Probability of a horizontal flip (vertical flips are not used: gravity matters underwater)."""
    brightness: float = bounded(0.15, ge=0, lt=1)
    """Additive brightness jitter, uniform in [-b, b]."""
    contrast: float = bounded(0.25, ge=0, lt=1)
    """Contrast factor jitter, uniform in [1-c, 1+c]."""
    saturation: float = bounded(0.25, ge=0, lt=1)
    """Saturation factor jitter, uniform in [1-s, 1+s]."""
    hue: float = bounded(0.05, ge=0, le=0.5)
    """Hue shift jitter, uniform in [-h, h] turns."""
    turbidity: float = bounded(0.3, ge=0, lt=1)
    """Largest blend weight toward a random blue-green water colour (haze)."""
    noise: float = bounded(0.01, ge=0)
    """Standard deviation of additive Gaussian pixel noise."""
    crop_prob: float = bounded(0.5, ge=0, le=1)
    """Probability of a random crop resized back to the full size."""
    crop_min: float = bounded(0.7, gt=0, le=1)
    """Smallest crop side as a fraction of the image side."""


def _uniform(g: torch.Generator, n: int, lo: float, hi: float, device: torch.device) -> torch.Tensor:
    return lo + (hi - lo) * torch.rand(n, generator=g, device=device)


def colour_jitter(image: torch.Tensor, g: torch.Generator, cfg: AugmentConfig) -> torch.Tensor:
    """Per-sample brightness/contrast/saturation/hue jitter, water haze and noise of ``(B, 3, H, W)`` in [0, 1]."""
    b, dev = image.shape[0], image.device
    x = image.float()
    x = ke.adjust_brightness(x, _uniform(g, b, -cfg.brightness, cfg.brightness, dev))
    x = ke.adjust_contrast(x, _uniform(g, b, 1 - cfg.contrast, 1 + cfg.contrast, dev))
    x = ke.adjust_saturation(x, _uniform(g, b, 1 - cfg.saturation, 1 + cfg.saturation, dev))
    x = ke.adjust_hue(x, _uniform(g, b, -cfg.hue, cfg.hue, dev) * 2 * torch.pi)
    t = _uniform(g, b, 0.0, cfg.turbidity, dev).view(b, 1, 1, 1)
    water = torch.stack([_uniform(g, b, 0.0, 0.2, dev), _uniform(g, b, 0.25, 0.5, dev),
                         _uniform(g, b, 0.3, 0.55, dev)], dim=1).view(b, 3, 1, 1)
    x = x * (1 - t) + water * t
    if cfg.noise > 0:
        x = x + cfg.noise * torch.randn(x.shape, generator=g, device=dev)
    return x.clamp(0, 1).to(image.dtype)


def _resize(t: torch.Tensor, size: tuple[int, int], nearest: bool) -> torch.Tensor:
    """Resize a (C, h, w) map; integer/bool maps and ``nearest`` use nearest neighbour."""
    if nearest or not t.is_floating_point():
        return F.interpolate(t[None].float(), size=size, mode="nearest")[0].to(t.dtype)
    return F.interpolate(t[None], size=size, mode="bilinear", align_corners=False)[0]


def augment_dense(batch: dict, g: torch.Generator, cfg: AugmentConfig) -> dict:
    """Augment a dense batch: ``image`` (B,3,H,W) and any of ``label`` (B,H,W), ``depth``/``valid``/``fg`` (B,1,H,W).

    Returns a new dict (the input tensors are not modified); other keys pass through.
    """
    if not cfg.enabled:
        return batch
    out = dict(batch)
    image = out["image"]
    b, _, h, w = image.shape
    dev = image.device
    flip = torch.rand(b, generator=g, device=dev) < cfg.hflip
    crop = torch.rand(b, generator=g, device=dev) < cfg.crop_prob
    side = _uniform(g, b, cfg.crop_min, 1.0, dev)
    oy, ox = torch.rand(b, generator=g, device=dev), torch.rand(b, generator=g, device=dev)
    keys = [k for k in ("image", "label", "depth", "valid", "fg") if k in out]
    for k in keys:
        out[k] = out[k].clone()
    for i in range(b):
        for k in keys:
            t = out[k][i]
            if bool(flip[i]):
                t = t.flip(-1)
            if bool(crop[i]):
                ch, cw = max(int(round(float(side[i]) * h)), 1), max(int(round(float(side[i]) * w)), 1)
                y0, x0 = int(float(oy[i]) * (h - ch)), int(float(ox[i]) * (w - cw))
                sub = t[..., y0 : y0 + ch, x0 : x0 + cw]
                t = _resize(sub if sub.ndim == 3 else sub[None], (h, w), nearest=k != "image")
                t = t if out[k][i].ndim == 3 else t[0]
                if k == "depth":
                    t = t * (ch / h)
            out[k][i] = t
    if "valid" in out and "depth" in out:
        out["valid"] = out["valid"] & (out["depth"] > 0)
    out["image"] = colour_jitter(out["image"], g, cfg)
    return out


def random_patches(batch: dict, g: torch.Generator, size: tuple[int, int], focus_prob: float = 0.5,
                   focus_weights: Sequence[float] | None = None) -> dict:
    """Cut one ``size`` = (h, w) window per sample from every dense key (no resizing: the camera is unchanged).

    With probability ``focus_prob`` the window is centred (clamped to the image) on a random pixel of a class
    drawn among the non-background classes present in the sample's ``label`` (uniformly, or with probability
    proportional to ``focus_weights[class]``, e.g. rarer classes more often), so small classes (valves, hot
    stabs) are seen in most batches; otherwise the window is uniform. Frames smaller than ``size`` are returned
    unchanged.
    """
    image = batch["image"]
    b, _, h, w = image.shape
    ph, pw = min(size[0], h), min(size[1], w)
    if (ph, pw) == (h, w):
        return batch
    dev = image.device
    out = dict(batch)
    keys = [k for k in ("image", "label", "depth", "valid", "fg") if k in out]
    crops: dict[str, list[torch.Tensor]] = {k: [] for k in keys}
    for i in range(b):
        y0 = int(torch.randint(0, h - ph + 1, (1,), generator=g, device=dev))
        x0 = int(torch.randint(0, w - pw + 1, (1,), generator=g, device=dev))
        focus = float(torch.rand(1, generator=g, device=dev)) < focus_prob
        if focus and "label" in out:
            lab = out["label"][i]
            classes = [int(c) for c in torch.unique(lab) if 0 < int(c) < 255]
            if classes:
                c = classes[_pick(classes, focus_weights, g, dev)]
                ys, xs = torch.nonzero(lab == c, as_tuple=True)
                j = int(torch.randint(0, len(ys), (1,), generator=g, device=dev))
                y0 = min(max(int(ys[j]) - ph // 2, 0), h - ph)
                x0 = min(max(int(xs[j]) - pw // 2, 0), w - pw)
        for k in keys:
            crops[k].append(out[k][i, ..., y0 : y0 + ph, x0 : x0 + pw])
    for k in keys:
        out[k] = torch.stack(crops[k])
    return out


def _pick(classes: list[int], weights: Sequence[float] | None, g: torch.Generator, dev: torch.device) -> int:
    """Index into ``classes`` drawn uniformly, or proportionally to ``weights[c]`` (uniform if all are 0)."""
    if weights is not None:
        w = torch.tensor([float(weights[c]) if c < len(weights) else 0.0 for c in classes], device=dev)
        if float(w.sum()) > 0:
            return int(torch.multinomial(w, 1, generator=g))
    return int(torch.randint(0, len(classes), (1,), generator=g, device=dev))

"""Seeded batch augmentations for dense tasks: colour and turbidity jitter, horizontal flips, crops.

Every random draw comes from the ``torch.Generator`` the training loop passes in (seeded per step), so a
resumed run augments exactly like an uninterrupted one. Geometric changes are applied to every dense target
in the batch: ``label`` (nearest), ``depth``/``valid`` (nearest) and an optional ``fg`` mask channel. A crop
of side fraction ``s`` resized back to full size magnifies the scene by ``1/s``, which for a fixed focal
length looks like the scene at ``s`` times the depth: depth targets are multiplied by ``s`` so the
image-to-depth relation stays that of the real camera.
"""

from __future__ import annotations

import math
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
    lamp_prob: float = bounded(0.0, ge=0, le=1)
    """Probability of a lamp hotspot: a tinted Gaussian gain field ``1 + a * tint * exp(-r^2 / 2 sigma^2)`` that
    brightens one spot as an ROV lamp lights a near part. 0 = off: it did not help the lamp-lit hot stab
    (docs/tuning/train_config.md#augmentconfiglamp_prob)."""
    lamp_gain: float = bounded(2.0, ge=0)
    """Largest extra gain ``a`` at the hotspot centre (drawn uniformly in [0, lamp_gain])."""
    lamp_sigma: tuple[float, float] = (0.05, 0.25)
    """Range of the hotspot's Gaussian radius ``sigma``, fraction of the image width (drawn uniformly)."""


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


def lamp_hotspot(image: torch.Tensor, g: torch.Generator, cfg: AugmentConfig,
                 label: torch.Tensor | None = None, class_weights: Sequence[float] | None = None) -> torch.Tensor:
    """Brighten a spot of each ``(B, 3, H, W)`` image in [0, 1] with probability ``cfg.lamp_prob`` (a lamp hotspot).

    The gain field is ``1 + a * tint_c * exp(-|p - p0|^2 / (2 sigma^2))`` per channel ``c``: ``a`` uniform in
    ``[0, lamp_gain]``, ``sigma`` uniform in ``lamp_sigma`` times the width, ``tint`` a random colour whose
    brightest channel is 1 (lamp light filtered by water). The centre ``p0`` is a label pixel of a class drawn
    with probability proportional to ``class_weights[c]`` among the classes present (then a uniform pixel of
    it), so rare parts are seen lit; uniform over the image without ``label``/``class_weights`` or when no
    weighted class is present. Pixel centres are at integer + 0.5. Returns a new tensor clamped to [0, 1].
    """
    b, _, h, w = image.shape
    dev = image.device
    on = torch.rand(b, generator=g, device=dev) < cfg.lamp_prob
    amp = _uniform(g, b, 0.0, cfg.lamp_gain, dev) * on
    sigma = _uniform(g, b, cfg.lamp_sigma[0], cfg.lamp_sigma[1], dev) * w
    tint = _uniform(g, 3 * b, 0.2, 1.0, dev).view(b, 3)
    tint = tint / tint.amax(1, keepdim=True)
    pix = torch.rand(b, h * w, generator=g, device=dev)  # uniform centre: argmax of uniform noise
    if label is not None and class_weights is not None:
        lab = label.reshape(b, -1)
        cw = torch.tensor([float(x) for x in class_weights], device=dev)
        known = lab < len(cw)
        onehot = torch.zeros(b, len(cw), device=dev).scatter_add_(1, torch.where(known, lab, 0),
                                                                  known.float())
        # per-pixel weight w_c / n_c: class c is drawn with probability ~ w_c, then a uniform pixel of it
        per_class = torch.where(onehot > 0, cw[None] / onehot.clamp(min=1), torch.zeros_like(onehot))
        pw = torch.where(known, per_class.gather(1, torch.where(known, lab, 0)), torch.zeros_like(pix))
        has = pw.sum(1, keepdim=True) > 0
        # weighted draw without a per-sample loop: argmax of u^(1/w) (exponential race), uniform where no weight
        race = torch.where(pw > 0, pix.clamp(min=1e-12).log() / pw.clamp(min=1e-30), torch.full_like(pix, -torch.inf))
        pix = torch.where(has, race, pix)
    idx = pix.argmax(1)
    cy, cx = (idx // w).float() + 0.5, (idx % w).float() + 0.5
    ys = torch.arange(h, device=dev, dtype=torch.float32) + 0.5
    xs = torch.arange(w, device=dev, dtype=torch.float32) + 0.5
    r2 = (ys[None, :, None] - cy[:, None, None]) ** 2 + (xs[None, None, :] - cx[:, None, None]) ** 2
    spot = torch.exp(-r2 / (2 * sigma[:, None, None] ** 2))
    gain = 1 + amp.view(b, 1, 1, 1) * tint.view(b, 3, 1, 1) * spot[:, None]
    return (image.float() * gain).clamp(0, 1).to(image.dtype)


def _resize(t: torch.Tensor, size: tuple[int, int], nearest: bool) -> torch.Tensor:
    """Resize a (C, h, w) map; integer/bool maps and ``nearest`` use nearest neighbour."""
    if nearest or not t.is_floating_point():
        return F.interpolate(t[None].float(), size=size, mode="nearest")[0].to(t.dtype)
    return F.interpolate(t[None], size=size, mode="bilinear", align_corners=False)[0]


def augment_dense(batch: dict, g: torch.Generator, cfg: AugmentConfig,
                  lamp_weights: Sequence[float] | None = None) -> dict:
    """Augment a dense batch: ``image`` (B,3,H,W) and any of ``label`` (B,H,W), ``depth``/``valid``/``fg`` (B,1,H,W).

    Geometry (flip, crop), then the lamp hotspot (centred by ``lamp_weights``, see :func:`lamp_hotspot`), then
    colour jitter. Returns a new dict (the input tensors are not modified); other keys pass through.
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
    if cfg.lamp_prob > 0:  # drawn only when on: configs without it keep their random stream
        out["image"] = lamp_hotspot(out["image"], g, cfg, out.get("label"), lamp_weights)
    out["image"] = colour_jitter(out["image"], g, cfg)
    return out


def random_patches(batch: dict, g: torch.Generator, size: tuple[int, int], focus_prob: float = 0.5,
                   focus_weights: Sequence[float] | None = None, zoom_prob: float = 0.0,
                   zoom_max: float = 1.0) -> dict:
    """Cut one ``size`` = (h, w) window per sample from every dense key (no resizing: the camera is unchanged).

    With probability ``focus_prob`` the window is centred (clamped to the image) on a random pixel of a class
    drawn among the non-background classes present in the sample's ``label`` (uniformly, or with probability
    proportional to ``focus_weights[class]``, e.g. rarer classes more often), so small classes (valves, hot
    stabs) are seen in most batches; otherwise the window is uniform. Frames smaller than ``size`` are returned
    unchanged.

    With probability ``zoom_prob`` a window is zoomed in instead: a ``size / z`` window around the same centre
    (clamped to the image), ``z`` log-uniform in ``[1, zoom_max]``, resampled to ``size`` (image bilinear, label,
    ``valid`` and ``fg`` nearest neighbour, depth nearest and divided by ``z``: the magnified view of a scene
    ``z`` times nearer through the same camera). The zoom draws are made only when ``zoom_prob > 0``.
    """
    image = batch["image"]
    b, _, h, w = image.shape
    ph, pw = min(size[0], h), min(size[1], w)
    if (ph, pw) == (h, w) and zoom_prob == 0:
        return batch
    dev = image.device
    out = dict(batch)
    keys = [k for k in ("image", "label", "depth", "valid", "fg") if k in out]
    crops: dict[str, list[torch.Tensor]] = {k: [] for k in keys}
    centres = []
    for i in range(b):
        y0 = int(torch.randint(0, h - ph + 1, (1,), generator=g, device=dev))
        x0 = int(torch.randint(0, w - pw + 1, (1,), generator=g, device=dev))
        cy, cx = y0 + ph / 2, x0 + pw / 2
        focus = float(torch.rand(1, generator=g, device=dev)) < focus_prob
        if focus and "label" in out:
            lab = out["label"][i]
            classes = [int(c) for c in torch.unique(lab) if 0 < int(c) < 255]
            if classes:
                c = classes[_pick(classes, focus_weights, g, dev)]
                ys, xs = torch.nonzero(lab == c, as_tuple=True)
                j = int(torch.randint(0, len(ys), (1,), generator=g, device=dev))
                cy, cx = int(ys[j]) + 0.5, int(xs[j]) + 0.5
                y0 = min(max(int(ys[j]) - ph // 2, 0), h - ph)
                x0 = min(max(int(xs[j]) - pw // 2, 0), w - pw)
        centres.append((cy, cx))
        for k in keys:
            crops[k].append(out[k][i, ..., y0 : y0 + ph, x0 : x0 + pw])
    for k in keys:
        out[k] = torch.stack(crops[k])
    if zoom_prob > 0:
        on = torch.rand(b, generator=g, device=dev) < zoom_prob
        z = torch.exp(torch.rand(b, generator=g, device=dev) * math.log(max(zoom_max, 1.0)))
        idx = [i for i in range(b) if bool(on[i]) and float(z[i]) > 1.0]
        if idx:
            zoomed = zoom_windows({k: batch[k][idx] for k in keys}, [centres[i] for i in idx],
                                  [float(z[i]) for i in idx], (ph, pw))
            for k in keys:
                out[k][idx] = zoomed[k].to(out[k].dtype)
    return out


def zoom_windows(batch: dict, centres: Sequence[tuple[float, float]], zooms: Sequence[float],
                 size: tuple[int, int]) -> dict:
    """Resample a ``(size[0] / z, size[1] / z)`` window of each sample, centred at ``(cy, cx)`` pixels (clamped
    inside the frame), to ``size``: image bilinear, ``label``/``valid``/``fg`` nearest, depth nearest divided by
    ``z``. Coordinates are continuous with pixel centres at integer + 0.5; batched (one ``grid_sample`` per key).

    >>> lab = torch.arange(16).view(1, 4, 4)
    >>> zoom_windows({"image": torch.zeros(1, 3, 4, 4), "label": lab}, [(1.0, 1.0)], [2.0], (4, 4))["label"][0, 0]
    tensor([0, 0, 1, 1])
    """
    image = batch["image"]
    n, _, h, w = image.shape
    ph, pw = size
    dev = image.device
    zt = torch.tensor([float(z) for z in zooms], device=dev)
    sh, sw = ph / zt, pw / zt  # window size in source pixels
    cy = torch.tensor([c[0] for c in centres], device=dev, dtype=torch.float32)
    cx = torch.tensor([c[1] for c in centres], device=dev, dtype=torch.float32)
    cy = torch.minimum(torch.maximum(cy, sh / 2), h - sh / 2)
    cx = torch.minimum(torch.maximum(cx, sw / 2), w - sw / 2)
    theta = torch.zeros(n, 2, 3, device=dev)
    theta[:, 0, 0], theta[:, 0, 2] = sw / w, 2 * cx / w - 1  # align_corners=False: -1/+1 are the frame edges
    theta[:, 1, 1], theta[:, 1, 2] = sh / h, 2 * cy / h - 1
    grid = F.affine_grid(theta, [n, 1, ph, pw], align_corners=False)
    out = dict(batch)
    for k in ("image", "label", "depth", "valid", "fg"):
        if k not in batch:
            continue
        t = batch[k]
        src = t[:, None].float() if t.ndim == 3 else t.float()
        r = F.grid_sample(src, grid, mode="bilinear" if k == "image" else "nearest", padding_mode="border",
                          align_corners=False)
        r = r[:, 0] if t.ndim == 3 else r
        if k == "depth":
            r = r / zt.view(n, 1, 1, 1)
        out[k] = r.round().to(t.dtype) if not t.is_floating_point() else r.to(t.dtype)
    return out


def _pick(classes: list[int], weights: Sequence[float] | None, g: torch.Generator, dev: torch.device) -> int:
    """Index into ``classes`` drawn uniformly, or proportionally to ``weights[c]`` (uniform if all are 0)."""
    if weights is not None:
        w = torch.tensor([float(weights[c]) if c < len(weights) else 0.0 for c in classes], device=dev)
        if float(w.sum()) > 0:
            return int(torch.multinomial(w, 1, generator=g))
    return int(torch.randint(0, len(classes), (1,), generator=g, device=dev))

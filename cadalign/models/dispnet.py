"""DispNet-style monocular depth: a strided encoder, a decoder with skips and multi-scale predictions.

The encoder halves the resolution ``levels`` times (7x7, 5x5, then 3x3 strided convs, each followed by a
3x3 conv); the decoder upsamples (4x4 transposed conv), concatenates the encoder skip and the upsampled
coarser prediction, and predicts at every scale. A raw prediction ``x`` becomes metric depth
``1 / (alpha * sigmoid(x) + beta)`` metres, so depth lies in ``(1/(alpha+beta), 1/beta)``:
:func:`alpha_beta_from_range` turns a depth range into ``alpha, beta`` (the defaults 7.203, 0.935 are the
thesis' values, a range of about 0.123 to 1.07 units).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from cadalign.config import bounded
from cadalign.models.resunet import pad_to_multiple


def alpha_beta_from_range(min_depth_m: float, max_depth_m: float) -> tuple[float, float]:
    """``(alpha, beta)`` so that ``1/(alpha*sigmoid(x)+beta)`` spans ``(min_depth_m, max_depth_m)``.

    >>> alpha_beta_from_range(0.5, 2.0)
    (1.5, 0.5)
    """
    if not 0 < min_depth_m < max_depth_m:
        raise ValueError(f"need 0 < min_depth_m < max_depth_m, got {min_depth_m}, {max_depth_m}")
    return 1.0 / min_depth_m - 1.0 / max_depth_m, 1.0 / max_depth_m


@dataclass(frozen=True)
class DispNetConfig:
    base_channels: int = bounded(32, ge=1)
    """Channels of the first encoder level; level i has ``base_channels * 2**min(i, 4)``."""
    levels: int = bounded(6, ge=2, le=7)
    """Number of stride-2 encoder levels (DispNet uses 6)."""
    in_channels: int = bounded(3, ge=1)
    """Input channels: 3 for RGB, 4 with a segmentation-mask channel."""
    alpha: float = bounded(7.203, gt=0)
    """Depth head ``1/(alpha*sigmoid(x)+beta)``: the inverse-depth span."""
    beta: float = bounded(0.935, gt=0)
    """Depth head: the inverse of the largest depth, 1/m."""


def _conv(cin: int, cout: int, k: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, k, stride=stride, padding=k // 2), nn.BatchNorm2d(cout),
                         nn.LeakyReLU(0.1, inplace=True))


class DispNet(nn.Module):
    """``(B, in_channels, H, W)`` -> depth ``(B, 1, H, W)`` metres; ``multiscale=True`` -> a list, finest first."""

    def __init__(self, cfg: DispNetConfig | None = None) -> None:
        super().__init__()
        cfg = cfg or DispNetConfig()
        self.cfg = cfg
        w = [cfg.base_channels * 2 ** min(i, 4) for i in range(cfg.levels)]
        ks = [7, 5] + [3] * (cfg.levels - 2)
        cins = [cfg.in_channels, *w[:-1]]
        self.enc = nn.ModuleList(nn.Sequential(_conv(ci, co, k, 2), _conv(co, co, 3))
                                 for ci, co, k in zip(cins, w, ks, strict=True))
        self.pred_top = nn.Conv2d(w[-1], 1, 3, padding=1)
        # decoder level i (coarse -> fine) produces w[i] channels at the resolution of encoder level i
        dec_out = [max(w[i] // 2, 8) for i in range(cfg.levels - 1)] + [w[-1]]
        self.upconv = nn.ModuleList()
        self.iconv = nn.ModuleList()
        self.pred = nn.ModuleList()
        for i in reversed(range(cfg.levels)):  # target resolution: encoder level i-1 (or the input at i == 0)
            skip_c = w[i - 1] if i > 0 else cfg.in_channels
            out_c = dec_out[i - 1] if i > 0 else max(cfg.base_channels // 2, 8)
            self.upconv.append(nn.Sequential(nn.ConvTranspose2d(dec_out[i] if i < cfg.levels - 1 else w[-1], out_c,
                                                                4, stride=2, padding=1), nn.LeakyReLU(0.1, True)))
            self.iconv.append(_conv(out_c + skip_c + 1, out_c, 3))
            self.pred.append(nn.Conv2d(out_c, 1, 3, padding=1))

    def to_depth(self, x: torch.Tensor) -> torch.Tensor:
        """Raw prediction -> metres, ``1/(alpha*sigmoid(x)+beta)`` (computed in float32)."""
        return 1.0 / (self.cfg.alpha * torch.sigmoid(x.float()) + self.cfg.beta)

    def forward(self, x: torch.Tensor, multiscale: bool = False) -> torch.Tensor | list[torch.Tensor]:
        if x.ndim != 4 or x.shape[1] != self.cfg.in_channels:
            raise ValueError(f"expected (B, {self.cfg.in_channels}, H, W), got {tuple(x.shape)}")
        h, w = x.shape[-2:]
        inp = pad_to_multiple(x, 2**self.cfg.levels)
        feats = [inp]
        for enc in self.enc:
            feats.append(enc(feats[-1]))
        y = feats[-1]
        raw = self.pred_top(y)
        outs = [raw]
        for up, iconv, pred, skip in zip(self.upconv, self.iconv, self.pred, reversed(feats[:-1]), strict=True):
            y = up(y)
            raw_up = F.interpolate(raw, size=y.shape[-2:], mode="bilinear", align_corners=False)
            y = iconv(torch.cat([y, skip, raw_up], dim=1))
            raw = pred(y) + raw_up
            outs.append(raw)
        scale_out = []
        for r in reversed(outs):
            s = inp.shape[-1] // r.shape[-1]
            scale_out.append(self.to_depth(r[..., : -(-h // s), : -(-w // s)]))
        return scale_out if multiscale else scale_out[0]

"""ResUNet: a U-Net of residual ConvBlocks for per-pixel classification.

Each ConvBlock is two (3x3 conv -> LeakyReLU(0.2) -> BatchNorm) with a residual connection (a 1x1 conv when
the channel count changes). The encoder has ``depth`` blocks (5 in the thesis) of ``base_channels * 2**i``
channels separated by 2x2 max pooling; the decoder upsamples (2x2 transposed conv), concatenates the encoder
skip and applies a ConvBlock; a 1x1 conv gives the class logits. Inputs of any size are padded (reflect) to a
multiple of ``2**(depth-1)`` and the logits cropped back, so the output is ``(B, n_classes, H, W)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from cadalign.config import bounded


@dataclass(frozen=True)
class ResUNetConfig:
    base_channels: int = bounded(32, ge=1)
    """Channels of the first ConvBlock; block i has ``base_channels * 2**i``."""
    depth: int = bounded(5, ge=2, le=7)
    """Number of encoder ConvBlocks (the thesis uses 5)."""
    in_channels: int = bounded(3, ge=1)
    """Input channels (3 for RGB)."""
    dropout: float = bounded(0.0, ge=0, lt=1)
    """Dropout before the classifier."""


class ConvBlock(nn.Module):
    """Two (3x3 conv -> LeakyReLU(0.2) -> BatchNorm) with a residual connection: ``(B,cin,H,W) -> (B,cout,H,W)``."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(cin, cout, 3, padding=1), nn.LeakyReLU(0.2, inplace=True), nn.BatchNorm2d(cout),
            nn.Conv2d(cout, cout, 3, padding=1), nn.LeakyReLU(0.2, inplace=True), nn.BatchNorm2d(cout),
        )
        self.skip = nn.Identity() if cin == cout else nn.Conv2d(cin, cout, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x) + self.skip(x)


class ResUNet(nn.Module):
    """``(B, in_channels, H, W)`` image in [0, 1] -> ``(B, n_classes, H, W)`` logits."""

    def __init__(self, n_classes: int, cfg: ResUNetConfig | None = None) -> None:
        super().__init__()
        cfg = cfg or ResUNetConfig()
        if n_classes < 2:
            raise ValueError(f"ResUNet needs at least 2 classes (background + one), got {n_classes}")
        self.cfg, self.n_classes = cfg, n_classes
        widths = [cfg.base_channels * 2**i for i in range(cfg.depth)]
        self.down = nn.ModuleList(
            ConvBlock(cin, cout) for cin, cout in zip([cfg.in_channels, *widths[:-1]], widths, strict=True)
        )
        self.up = nn.ModuleList(nn.ConvTranspose2d(widths[i + 1], widths[i], 2, stride=2)
                                for i in reversed(range(cfg.depth - 1)))
        self.dec = nn.ModuleList(ConvBlock(2 * widths[i], widths[i]) for i in reversed(range(cfg.depth - 1)))
        self.drop = nn.Dropout2d(cfg.dropout) if cfg.dropout > 0 else nn.Identity()
        self.head = nn.Conv2d(widths[0], n_classes, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 4 or x.shape[1] != self.cfg.in_channels:
            raise ValueError(f"expected (B, {self.cfg.in_channels}, H, W), got {tuple(x.shape)}")
        h, w = x.shape[-2:]
        x = pad_to_multiple(x, 2 ** (self.cfg.depth - 1))
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else F.max_pool2d(x, 2))
            skips.append(x)
        for up, dec, skip in zip(self.up, self.dec, reversed(skips[:-1]), strict=True):
            x = dec(torch.cat([up(x), skip], dim=1))
        return self.head(self.drop(x))[..., :h, :w]


def pad_to_multiple(x: torch.Tensor, m: int) -> torch.Tensor:
    """Pad ``(B, C, H, W)`` at the bottom/right (reflect, replicate when too small) to multiples of ``m``."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % m, (-w) % m
    if ph == 0 and pw == 0:
        return x
    mode = "reflect" if ph < h and pw < w else "replicate"
    return F.pad(x, (0, pw, 0, ph), mode=mode)

"""Optional super-resolution of a photo before depth (GenLaM's Real-ESRGAN step), from a user-given checkpoint.

Real-ESRGAN's generator is ESRGAN's RRDB network; its ``.pth`` files hold a state dict (under ``params_ema``
or ``params``) that this module's :class:`RRDBNet` loads strictly, in plain torch, without basicsr. The
network's size is read from the state dict: feature width, number of RRDB blocks, growth channels, and the
scale from the input channels of ``conv_first`` (3: x4; 12: x2 and 48: x1, where the input is first
pixel-unshuffled by 2 or 4). Input and output are RGB in [0, 1].

Not measured: no Real-ESRGAN checkpoint nor a depth network that works on real photos was available, so
whether the step lowers the depth error is unknown (docs/tuning/genlam_photo.md). It is off unless
``--sr-model`` is given.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from cadalign.errors import InputError

log = logging.getLogger(__name__)


class _DenseBlock(nn.Module):
    """Five 3x3 convolutions, each seeing the input and all earlier outputs; residual scaled by 0.2."""

    def __init__(self, feat: int, grow: int) -> None:
        super().__init__()
        for i in range(1, 6):
            setattr(self, f"conv{i}", nn.Conv2d(feat + (i - 1) * grow, feat if i == 5 else grow, 3, 1, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        outs = [x]
        for i in range(1, 5):
            outs.append(F.leaky_relu(getattr(self, f"conv{i}")(torch.cat(outs, 1)), 0.2))
        return x + 0.2 * self.conv5(torch.cat(outs, 1))


class _RRDB(nn.Module):
    def __init__(self, feat: int, grow: int) -> None:
        super().__init__()
        self.rdb1, self.rdb2, self.rdb3 = (_DenseBlock(feat, grow) for _ in range(3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + 0.2 * self.rdb3(self.rdb2(self.rdb1(x)))


class RRDBNet(nn.Module):
    """ESRGAN / Real-ESRGAN generator (parameter names as in the published checkpoints).

    Args:
        scale: output size over input size: 4, 2 or 1.
        feat: feature channels. blocks: RRDB blocks. grow: growth channels of a dense block.
    """

    def __init__(self, scale: int = 4, feat: int = 64, blocks: int = 23, grow: int = 32) -> None:
        super().__init__()
        self.scale = scale
        self.unshuffle = {4: 1, 2: 2, 1: 4}[scale]
        self.conv_first = nn.Conv2d(3 * self.unshuffle**2, feat, 3, 1, 1)
        self.body = nn.Sequential(*(_RRDB(feat, grow) for _ in range(blocks)))
        self.conv_body = nn.Conv2d(feat, feat, 3, 1, 1)
        self.conv_up1 = nn.Conv2d(feat, feat, 3, 1, 1)
        self.conv_up2 = nn.Conv2d(feat, feat, 3, 1, 1)
        self.conv_hr = nn.Conv2d(feat, feat, 3, 1, 1)
        self.conv_last = nn.Conv2d(feat, 3, 3, 1, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [0, 1] (H, W divisible by the unshuffle factor) -> (B, 3, scale H, scale W)."""
        feat = F.pixel_unshuffle(x, self.unshuffle) if self.unshuffle > 1 else x
        feat = self.conv_first(feat)
        feat = feat + self.conv_body(self.body(feat))
        for conv in (self.conv_up1, self.conv_up2):
            feat = F.leaky_relu(conv(F.interpolate(feat, scale_factor=2, mode="nearest")), 0.2)
        return self.conv_last(F.leaky_relu(self.conv_hr(feat), 0.2))


def _state_dict(path: Path) -> dict[str, torch.Tensor]:
    path = Path(path)
    if not path.is_file():
        raise InputError(f"--sr-model {path} not found; give a Real-ESRGAN / ESRGAN RRDBNet .pth file")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for foreign or corrupt files
        raise InputError(f"--sr-model {path}: not a torch state dict ({exc})") from exc
    for key in ("params_ema", "params", "state_dict"):
        if isinstance(obj, dict) and key in obj and isinstance(obj[key], dict):
            return obj[key]
    if not isinstance(obj, dict) or "conv_first.weight" not in obj:
        raise InputError(f"--sr-model {path}: no RRDBNet weights (conv_first.weight) found; only the Real-ESRGAN "
                         "/ ESRGAN RRDBNet generator is supported (not SRVGG 'compact' or SwinIR models)")
    return obj


def load_sr_model(path: Path, device: str = "cpu") -> Callable[[np.ndarray], np.ndarray]:
    """A Real-ESRGAN checkpoint -> ``upscale(rgb (H, W, 3) uint8) -> (s H, s W, 3) uint8``.

    Raises:
        InputError: missing file, not a state dict, or weights of another architecture.
    """
    sd = _state_dict(path)
    if "conv_first.weight" not in sd:
        raise InputError(f"--sr-model {path}: no conv_first.weight; only RRDBNet (Real-ESRGAN x4plus / x2plus) "
                         "checkpoints are supported")
    feat, in_ch = sd["conv_first.weight"].shape[:2]
    scale = {3: 4, 12: 2, 48: 1}.get(int(in_ch))
    blocks = 1 + max((int(m.group(1)) for k in sd if (m := re.match(r"body\.(\d+)\.", k))), default=-1)
    if scale is None or blocks == 0 or "body.0.rdb1.conv1.weight" not in sd:
        raise InputError(f"--sr-model {path}: conv_first has {in_ch} input channels and {blocks} RRDB blocks; "
                         "not an RRDBNet generator (3, 12 or 48 input channels)")
    net = RRDBNet(scale, int(feat), blocks, int(sd["body.0.rdb1.conv1.weight"].shape[0]))
    try:
        net.load_state_dict(sd, strict=True)
    except RuntimeError as exc:
        raise InputError(f"--sr-model {path}: weights do not fit an RRDBNet: {exc}") from exc
    net = net.to(device).eval()
    log.info("super-resolution %s: RRDBNet x%d, %d blocks, %d features", path, scale, blocks, feat)

    def upscale(rgb: np.ndarray) -> np.ndarray:
        H, W = np.shape(rgb)[:2]
        m = net.unshuffle
        x = torch.from_numpy(np.ascontiguousarray(rgb[..., :3].transpose(2, 0, 1))).float()[None] / 255.0
        x = F.pad(x, (0, (-W) % m, 0, (-H) % m), mode="replicate")
        with torch.inference_mode():
            y = net(x.to(device))[..., : scale * H, : scale * W]
        return (y[0].clamp(0, 1) * 255).round().byte().permute(1, 2, 0).cpu().numpy()

    return upscale

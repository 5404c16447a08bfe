"""Anchor boxes on each pyramid level.

Anchors of level ``l`` (stride ``s``) are centred on the feature cells' centres ``((x + .5) s, (y + .5) s)``
in input pixels (pixel centres at integer + 0.5); each cell has one anchor per aspect ratio ``h / w`` with
area ``size^2``. Order: row-major over cells, aspect ratios fastest — the same order as the RPN head's
``(A, H, W)`` outputs after :func:`flatten_level`.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def cell_anchors(size: float, ratios: Sequence[float], dtype: torch.dtype = torch.float32) -> Tensor:
    """``(A, 4)`` anchors centred on (0, 0): ``w = size / sqrt(r)``, ``h = size * sqrt(r)``."""
    r = torch.as_tensor(ratios, dtype=dtype)
    h = size * torch.sqrt(r)
    w = size / torch.sqrt(r)
    return torch.stack([-w / 2, -h / 2, w / 2, h / 2], 1)


def grid_anchors(feat_hw: tuple[int, int], stride: int, size: float | Sequence[float], ratios: Sequence[float],
                 device: torch.device | str = "cpu") -> Tensor:
    """``(H * W * A, 4)`` xyxy anchors of one level with a ``feat_hw`` feature map.

    ``size`` may be several sizes (scales within the level, RetinaNet's ``2^(k/3)``): ``A = sizes x ratios``,
    size-major, ratios fastest.
    """
    h, w = feat_hw
    ys = (torch.arange(h, dtype=torch.float32, device=device) + 0.5) * stride
    xs = (torch.arange(w, dtype=torch.float32, device=device) + 0.5) * stride
    cy, cx = torch.meshgrid(ys, xs, indexing="ij")
    shifts = torch.stack([cx, cy, cx, cy], -1).reshape(-1, 1, 4)
    sizes = [float(size)] if isinstance(size, (int, float)) else [float(v) for v in size]
    cell = torch.cat([cell_anchors(v, ratios) for v in sizes]).to(device)
    return (shifts + cell[None]).reshape(-1, 4)


def flatten_level(x: Tensor, k: int) -> Tensor:
    """Head output ``(N, A*k, H, W)`` -> ``(N, H*W*A, k)`` in anchor order."""
    n, ak, h, w = x.shape
    return x.view(n, ak // k, k, h, w).permute(0, 3, 4, 1, 2).reshape(n, -1, k)

"""ResUNet and DispNet: shapes on odd sizes, depth head range, config errors, gradients."""

from __future__ import annotations

import pytest
import torch

from cadalign.models.dispnet import DispNet, DispNetConfig, alpha_beta_from_range
from cadalign.models.resunet import ConvBlock, ResUNet, ResUNetConfig


@pytest.mark.parametrize("hw", [(48, 64), (37, 50), (8, 8)])
def test_resunet_any_size(hw):
    torch.manual_seed(0)
    m = ResUNet(4, ResUNetConfig(base_channels=4, depth=5)).eval()
    assert m(torch.rand(2, 3, *hw)).shape == (2, 4, *hw)


def test_resunet_structure_and_errors():
    m = ResUNet(3, ResUNetConfig(base_channels=4, depth=5))
    assert len(m.down) == 5 and all(isinstance(b, ConvBlock) for b in m.down)
    block = m.down[0].body
    assert isinstance(block[0], torch.nn.Conv2d) and block[0].kernel_size == (3, 3)
    assert isinstance(block[1], torch.nn.LeakyReLU) and block[1].negative_slope == 0.2
    assert isinstance(block[2], torch.nn.BatchNorm2d)
    with pytest.raises(ValueError, match="at least 2 classes"):
        ResUNet(1)
    with pytest.raises(ValueError, match=r"expected \(B, 3, H, W\)"):
        m(torch.rand(1, 4, 16, 16))


def test_conv_block_is_residual():
    b = ConvBlock(4, 4)
    for p in b.body.parameters():
        torch.nn.init.zeros_(p)
    x = torch.rand(1, 4, 5, 5)
    assert torch.allclose(b(x), x)  # body outputs 0 (BN beta 0): only the skip remains


def test_alpha_beta_round_trip():
    a, b = alpha_beta_from_range(0.5, 20.0)
    assert 1 / b == pytest.approx(20.0) and 1 / (a + b) == pytest.approx(0.5)
    with pytest.raises(ValueError):
        alpha_beta_from_range(2.0, 1.0)
    assert DispNetConfig().alpha == 7.203 and DispNetConfig().beta == 0.935


@pytest.mark.parametrize("hw", [(48, 64), (30, 41)])
def test_dispnet_shapes_and_range(hw):
    torch.manual_seed(0)
    a, b = alpha_beta_from_range(1.0, 10.0)
    m = DispNet(DispNetConfig(base_channels=4, levels=4, alpha=a, beta=b))
    with torch.no_grad():
        outs = m(torch.rand(2, 3, *hw) * 50, multiscale=True)  # large inputs push the head to its limits
    assert len(outs) == 5 and outs[0].shape == (2, 1, *hw)
    assert outs[1].shape[-2:] == (-(-hw[0] // 2), -(-hw[1] // 2))
    for o in outs:
        assert float(o.min()) >= 1.0 - 1e-5 and float(o.max()) <= 10.0 + 1e-4
    m.eval()
    assert m(torch.rand(1, 3, *hw)).shape == (1, 1, *hw)


def test_dispnet_mask_channel_and_gradients():
    m = DispNet(DispNetConfig(base_channels=4, levels=3, in_channels=4))
    x = torch.rand(2, 4, 24, 32, requires_grad=True)
    m(x).mean().backward()
    assert x.grad is not None and torch.isfinite(x.grad).all() and float(x.grad[:, 3].abs().sum()) > 0
    with pytest.raises(ValueError, match=r"\(B, 4, H, W\)"):
        m(torch.rand(1, 3, 24, 32))

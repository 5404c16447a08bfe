"""Flip test-time augmentation of the dense seg inference: the mean of the frame's and its mirror's passes."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from cadalign.infer.dense import DenseModel, seg_probabilities
from cadalign.models.resunet import ResUNet, ResUNetConfig


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_flip_tta_is_the_mean_of_the_two_passes(scale):
    torch.manual_seed(0)
    net = ResUNet(4, ResUNetConfig(base_channels=4, depth=3)).eval()
    dm = DenseModel("seg", net, ("background", "a", "b", "c"), scale, False, torch.device("cpu"), Path("x.pt"), 0)
    image = torch.rand(2, 3, 24, 32)
    plain = seg_probabilities(dm, image)
    mirror = seg_probabilities(dm, image.flip(-1))
    tta = seg_probabilities(dm, image, flip_tta=True)
    assert tta.shape == (2, 4, 24, 32)
    assert torch.allclose(tta, 0.5 * (plain + mirror.flip(-1)), atol=1e-6)
    assert torch.allclose(tta.sum(1), torch.ones(2, 24, 32), atol=1e-5)
    assert not torch.allclose(tta, plain, atol=1e-4)  # a random net is not mirror symmetric
    # a mirror-symmetric image gives a mirror-symmetric TTA map
    sym = torch.cat([image[..., :16], image[..., :16].flip(-1)], -1)
    s = seg_probabilities(dm, sym, flip_tta=True)
    assert torch.allclose(s, s.flip(-1), atol=1e-5)


def test_seg_runs_channels_last_with_the_nchw_probabilities():
    """The ResUNet is fed channels-last (oneDNN then needs no layout reorder per layer: 0.45-0.75x the CPU time on
    640x480 frames, docs/tuning/demo_time.md) and gives the NCHW probabilities to float rounding, NCHW-ordered."""
    torch.manual_seed(0)
    net = ResUNet(4, ResUNetConfig(base_channels=4, depth=3)).eval()
    image = torch.rand(1, 3, 24, 32)
    with torch.no_grad():
        ref = net(image).softmax(1)
    seen = []
    net.register_forward_pre_hook(lambda m, a: seen.append(a[0].is_contiguous(memory_format=torch.channels_last)))
    dm = DenseModel("seg", net, ("background", "a", "b", "c"), 1.0, False, torch.device("cpu"), Path("x.pt"), 0)
    prob = seg_probabilities(dm, image)
    assert seen == [True]
    assert prob.is_contiguous() and torch.allclose(prob, ref, atol=1e-6)

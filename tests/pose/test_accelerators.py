"""The optional accelerators: torchvision's compiled RoIAlign/NMS and a CUDA device.

Neither exists on the CPU machines the suite normally runs on (torchvision's compiled ops do not load with the
CPU torch build, and there is no GPU), so these tests are skipped there. They run where the accelerators do:
on a GPU machine with torchvision, ``python -m pytest tests/pose/test_accelerators.py tests/pose/test_ops.py``
checks that the accelerated path gives the pure-torch path's numbers (and ``test_ops`` then checks the
accelerated path against the scalar reference kernels, since ``use_accel`` defaults to True). The
``test_pure_*_on_cuda`` tests run the pure-torch path on the GPU against the CPU (where torchvision's kernels do
not load there). All of them passed on an H200 (torch 2.11, torchvision 0.26) on Nov 27 2026, as did
``test_ops``, ``test_anchors``, ``test_maskrcnn`` (less its CLI test, which renders a scene) and
``tests/train/test_loop.py``.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from pose_testutils import TINY_K as K
from pose_testutils import tiny_cfg, tiny_pose_loss, tiny_scene

from cadalign.models.maskrcnn import MaskRCNNPose
from cadalign.models.ops import _tv_ops, batched_nms, nms, roi_align

CUDA = torch.cuda.is_available()
DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not CUDA, reason="no CUDA device here"))]
needs_tv = pytest.mark.skipif(_tv_ops() is None, reason="torchvision's compiled ops do not load here")


def _rois(n: int, h: int, w: int, g: torch.Generator) -> torch.Tensor:
    """Random RoIs in image pixels, including sub-pixel, inverted and partly outside boxes."""
    x0 = torch.rand(n, generator=g) * (w * 1.2) - 0.1 * w
    y0 = torch.rand(n, generator=g) * (h * 1.2) - 0.1 * h
    size = torch.exp(torch.rand(n, 2, generator=g) * 6 - 2)  # 0.14 .. 55 px
    boxes = torch.stack([x0, y0, x0 + size[:, 0], y0 + size[:, 1]], 1)
    boxes[:3] = boxes[:3, [2, 3, 0, 1]]  # three inverted boxes
    batch = torch.randint(0, 2, (n, 1), generator=g).float()
    return torch.cat([batch, boxes], 1)


@needs_tv
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("aligned", [True, False])
@pytest.mark.parametrize("sampling_ratio", [-1, 2])
def test_accelerated_roi_align_matches_pure(device: str, aligned: bool, sampling_ratio: int):
    g = torch.Generator().manual_seed(3)
    feat = torch.rand(2, 5, 40, 56, generator=g, dtype=torch.float64).to(device)
    rois = _rois(200, 160, 224, g).to(device, torch.float64)
    args = (feat, rois, (7, 7), 0.25, sampling_ratio, aligned)
    pure, accel = roi_align(*args, use_accel=False), roi_align(*args, use_accel=True)
    assert pure.device.type == device and accel.device.type == device
    torch.testing.assert_close(accel, pure, rtol=1e-9, atol=1e-9)
    # gradients with respect to the features agree too
    gp, ga = (torch.autograd.grad((roi_align(feat.requires_grad_(), rois, (7, 7), 0.25, sampling_ratio, aligned,
                                             use_accel=a) ** 2).sum(), feat)[0] for a in (False, True))
    torch.testing.assert_close(ga, gp, rtol=1e-9, atol=1e-9)


@needs_tv
@pytest.mark.parametrize("device", DEVICES)
def test_accelerated_nms_matches_pure(device: str):
    g = torch.Generator().manual_seed(4)
    for trial in range(20):
        n = 5 + trial * 20
        xy = torch.rand(n, 2, generator=g) * 100
        boxes = torch.cat([xy, xy + 5 + torch.rand(n, 2, generator=g) * 30], 1).to(device)
        scores = torch.randperm(n, generator=g).float().to(device)  # distinct: the order of ties is free
        cls = torch.randint(0, 3, (n,), generator=g).to(device)
        for thr in (0.3, 0.5, 0.7):
            pure, accel = nms(boxes, scores, thr, use_accel=False), nms(boxes, scores, thr, use_accel=True)
            assert torch.equal(pure, accel), (trial, thr)
            assert torch.equal(nms(boxes, scores, thr, max_keep=3, use_accel=True), pure[:3])
        kept = batched_nms(boxes, scores, cls, 0.5)
        assert kept.device.type == device
        for c in range(3):  # per category, the kept set is that category's own NMS
            sel = torch.nonzero(cls == c).squeeze(1)
            own = sel[nms(boxes[sel], scores[sel], 0.5, use_accel=False)]
            assert set(kept[cls[kept] == c].tolist()) == set(own.tolist())


@pytest.mark.skipif(not CUDA, reason="no CUDA device here")
def test_detector_trains_and_infers_on_cuda_like_on_cpu():
    """A few steps on the GPU learn as on the CPU, and the trained network detects the same objects on both."""
    torch.manual_seed(0)
    model = MaskRCNNPose(tiny_cfg(), ["background", "square", "bar"]).cuda()
    img, tgt = tiny_scene(0)
    img = img.cuda()
    tgt = {k: v.cuda() for k, v in tgt.items()}
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    totals = []
    for _ in range(100):
        losses = model(img[None], [tgt], pose_loss=tiny_pose_loss())
        assert all(v.device.type == "cuda" for v in losses.values())
        total = sum(losses.values())
        opt.zero_grad()
        total.backward()
        opt.step()
        totals.append(float(total.detach()))
    assert np.isfinite(totals).all() and np.mean(totals[-5:]) < 0.6 * totals[0], totals
    model.eval()
    cpu = copy.deepcopy(model).cpu()
    torch.backends.cudnn.allow_tf32 = False  # compare exact float32 arithmetic, not TF32 convolutions
    torch.backends.cuda.matmul.allow_tf32 = False
    d_gpu = model.detect(img, K.cuda(), score_thresh=0.1)
    d_cpu = cpu.detect(img.cpu(), K, score_thresh=0.1)
    assert len(d_cpu) >= 2 and len(d_gpu) == len(d_cpu)
    for a, b in zip(d_gpu, d_cpu, strict=True):
        assert a.label == b.label and abs(a.score - b.score) < 1e-3
        np.testing.assert_allclose(a.box_xyxy, b.box_xyxy, atol=0.05)
        np.testing.assert_allclose(a.t_cam_from_obj_m, b.t_cam_from_obj_m, atol=1e-3)
        assert (a.mask != b.mask).mean() < 0.01


@pytest.mark.skipif(not CUDA, reason="no CUDA device here")
@pytest.mark.parametrize("aligned", [True, False])
@pytest.mark.parametrize("sampling_ratio", [-1, 2])
def test_pure_roi_align_on_cuda_matches_cpu(aligned: bool, sampling_ratio: int):
    """The pure-torch RoIAlign (one embedding_bag per sampling-grid group) gives the CPU's numbers and gradients
    on a GPU, where it runs when torchvision's kernels do not load."""
    g = torch.Generator().manual_seed(5)
    feat = torch.rand(2, 5, 40, 56, generator=g, dtype=torch.float64)
    rois = _rois(300, 160, 224, g).double()
    outs, grads = [], []
    for dev in ("cpu", "cuda"):
        f = feat.to(dev).requires_grad_()
        out = roi_align(f, rois.to(dev), (7, 7), 0.25, sampling_ratio, aligned, use_accel=False)
        assert out.device.type == dev
        outs.append(out.detach().cpu())
        grads.append(torch.autograd.grad((out ** 2).sum(), f)[0].cpu())
    torch.testing.assert_close(outs[1], outs[0], rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-9, atol=1e-9)


@pytest.mark.skipif(not CUDA, reason="no CUDA device here")
def test_pure_roi_align_keeps_coordinates_precise_for_bf16_on_cuda():
    """As on the CPU (test_ops): bf16 features under CUDA autocast must not round a 150.3 px box corner to 150."""
    ramp = (torch.arange(200, dtype=torch.float32, device="cuda") - 100).expand(1, 1, 4, 200).contiguous()
    rois = torch.tensor([[0, 150.3, 1.0, 152.3, 3.0]], device="cuda")
    with torch.autocast("cuda", dtype=torch.bfloat16):
        feat = torch.nn.functional.conv2d(ramp, torch.ones(1, 1, 1, 1, device="cuda"))  # bf16 under autocast
        assert feat.dtype == torch.bfloat16
        out = roi_align(feat, rois, 1, 1.0, 1, True, use_accel=False)
    assert out.dtype == torch.bfloat16
    assert abs(float(out) - 50.8) <= 0.06


@pytest.mark.skipif(not CUDA, reason="no CUDA device here")
def test_pure_nms_on_cuda_matches_cpu_with_and_without_max_keep():
    """The pure NMS (blockwise first-kept search when ``max_keep`` < N) keeps the same boxes for CUDA inputs,
    returned on the GPU."""
    g = torch.Generator().manual_seed(6)
    xy = torch.rand(3000, 2, generator=g) * 300
    boxes = torch.cat([xy, xy + 4 + torch.rand(3000, 2, generator=g) * 40], 1)
    scores = torch.rand(3000, generator=g)
    for thr in (0.3, 0.7):
        full = nms(boxes, scores, thr, use_accel=False)
        for max_keep in (None, 50, 400):
            got = nms(boxes.cuda(), scores.cuda(), thr, max_keep=max_keep, use_accel=False)
            assert got.device.type == "cuda"
            assert torch.equal(got.cpu(), full[:max_keep]), (thr, max_keep)

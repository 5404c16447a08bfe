"""Accuracy and time of each preset on the reference frame case and the default scene (slow: ``-m slow -s``)."""

from __future__ import annotations

import time

import pytest
from align_testdata import sim3_errors

from cadalign.align import PRESETS, align, sample_surface


@pytest.mark.slow
@pytest.mark.parametrize("case", ["frame", "default_scene"])
@pytest.mark.parametrize("preset", ["fast", "balanced", "accurate"])
def test_preset_accuracy_and_time(preset, case, request):
    if case == "frame":
        parts, cloud = request.getfixturevalue("parts"), request.getfixturevalue("cloud")
    else:
        parts, cloud = request.getfixturevalue("default_scene")
    cfg = PRESETS[preset]
    t0 = time.perf_counter()
    surface = sample_surface(parts, cfg.cad_samples, cfg.seed)
    t1 = time.perf_counter()
    r = align(cloud.points_sfm, surface, cfg)
    seconds = time.perf_counter() - t0
    rot, trans, scale = sim3_errors(r.cad_from_sfm, cloud.cad_from_sfm, cloud.points_sfm)
    stages = ", ".join(f"{k} {v:.2f}" for k, v in {**r.seconds, "sample": t1 - t0}.items())
    print(f"\n{case:13s} {preset:9s} rot {rot:.4f} deg  trans {trans * 100:.3f} cm  scale {scale * 100:.4f} %  "
          f"total {seconds:.2f} s ({stages})")
    assert rot <= 0.3 and trans <= 0.02 and scale <= 0.005

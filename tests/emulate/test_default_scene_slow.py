"""Benchmark-sized checks on the default scene (deselected by default: ``pytest -m slow``)."""

from __future__ import annotations

import numpy as np
import pytest

from cadalign.bench.emulate import agreement
from cadalign.emulate.lidar import uniform_sphere


@pytest.mark.slow
def test_engines_agree_on_the_default_scene(shared_data) -> None:
    from cadalign.emulate.sources import scene_mesh
    from cadalign.sim.spec import default_scene_path, load_scene
    from cadalign.sim.trajectory import frame_poses

    spec = load_scene(default_scene_path())
    mesh = scene_mesh(default_scene_path())
    cams = frame_poses(spec.trajectory, 8, spec.seed)
    origins = np.concatenate([np.tile(c.t, (2500, 1)) for c in cams])
    a = agreement(mesh, origins, uniform_sphere(len(origins), np.random.default_rng(7)))
    assert a["agree_fraction"] >= 0.999 and a["class_agree_fraction"] >= 0.999 and a["hits"] > 5000

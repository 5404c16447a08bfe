"""Undeclared symmetries: found on symmetric point sets, not on asymmetric ones, silent when declared."""

from __future__ import annotations

import logging

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.cad.symmetry import Symmetry
from cadalign.metrics.pose_symmetry import CANDIDATES, symmetry_deviation, undeclared_symmetries, warn_undeclared


def _box(a: float, b: float, c: float, n: int = 6) -> np.ndarray:
    """Grid points on the surface of the box [-a, a] x [-b, b] x [0, c] (symmetric under Rz180, not Rx180)."""
    g = np.linspace(0, 1, n)
    u, v = np.meshgrid(g, g)
    u, v = u.ravel(), v.ravel()
    faces = []
    for x in (-a, a):
        faces.append(np.stack([np.full_like(u, x), -b + 2 * b * u, c * v], 1))
    for y in (-b, b):
        faces.append(np.stack([-a + 2 * a * u, np.full_like(u, y), c * v], 1))
    for z in (0.0, c):
        faces.append(np.stack([-a + 2 * a * u, -b + 2 * b * v, np.full_like(u, z)], 1))
    return np.unique(np.concatenate(faces).round(12), axis=0)


def _diam(p: np.ndarray) -> float:
    return float(np.linalg.norm(p.max(0) - p.min(0)))


def test_box_half_turn_found_and_handle_breaks_it():
    box = _box(0.2, 0.35, 0.5)
    names = [f.name for f in undeclared_symmetries(box, _diam(box), Symmetry.none())]
    assert names == ["Rz180"]
    assert symmetry_deviation(box, CANDIDATES["Rz180"], _diam(box)) < 1e-9
    handle = np.concatenate([box, np.array([[0.2 + 0.1 * k, 0.0, 0.25] for k in range(1, 4)])])
    assert undeclared_symmetries(handle, _diam(handle), Symmetry.none()) == []
    square = _box(0.3, 0.3, 0.5)
    assert {f.name for f in undeclared_symmetries(square, _diam(square), Symmetry.none())} == {"Rz180", "Rz90"}


def test_declared_symmetries_are_not_reported(caplog):
    box = _box(0.2, 0.35, 0.5)
    declared = Symmetry.cyclic((0.0, 0.0, 1.0), 2)
    assert undeclared_symmetries(box, _diam(box), declared) == []
    assert undeclared_symmetries(box, _diam(box), Symmetry.continuous((0.0, 0.0, 1.0))) == []
    with caplog.at_level(logging.WARNING):
        found = warn_undeclared({3: (box, _diam(box), Symmetry.none()), 4: (box, _diam(box), declared)})
    assert found == {3: ["Rz180"]} and "model 3 is invariant to Rz180" in caplog.text


@settings(max_examples=15, deadline=None)
@given(st.integers(0, 10_000))
def test_random_point_clouds_have_no_symmetry(seed: int):
    pts = np.random.default_rng(seed).normal(size=(60, 3))
    assert undeclared_symmetries(pts, _diam(pts), Symmetry.none()) == []


def test_the_run_evaluation_checks_only_the_pose_targets(tiny_sim):
    """The tiny scene's structure block is a box (invariant to half turns) but no pose target: an evaluation
    names only the parts it scores (the valve and hot stab declare no symmetry there)."""
    from cadalign.infer.run import evaluate_run
    from cadalign.io import read_json

    scene = tiny_sim / "gt" / "sim" / "000000"
    objs = read_json(scene / "objects.json")["objects"]
    obj_of = {o["name"]: str(o["obj_id"]) for o in objs}
    rep = evaluate_run([], ["000000.png"], scene, None)
    found = rep["fused"]["config"]["undeclared_symmetries"]
    assert obj_of["block"] not in found
    assert obj_of["valve"] in found and "Rz180" in found[obj_of["valve"]]

"""SE(3) / Sim(3): Rigid3, Sim3 and the transforms helpers (compose, invert, apply, decompose)."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_testdata import DETERMINISTIC, random_sim3_parts, rotation_error, seeds
from hypothesis import given, settings

from cadalign.errors import InputError
from cadalign.geometry import (
    compose,
    invert,
    random_rotation,
    relative_pose_error,
    sim3_from_matrix,
    transform_points,
)
from cadalign.types import Rigid3, Sim3


def _rigid(rng: np.random.Generator) -> Rigid3:
    return Rigid3(random_rotation(rng), rng.uniform(-10, 10, 3))


def _sim(rng: np.random.Generator) -> Sim3:
    return Sim3(*random_sim3_parts(rng))


def _homogeneous_apply(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    xh = np.concatenate([x, np.ones((x.shape[0], 1))], axis=1)
    return (xh @ M.T)[:, :3]


@settings(max_examples=30, **DETERMINISTIC)
@given(seeds)
def test_rigid_inverse_compose_apply(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T, U, V = _rigid(rng), _rigid(rng), _rigid(rng)
    x = rng.uniform(-5, 5, (20, 3))
    for ident in (T.inverse() @ T, T @ T.inverse()):
        assert np.allclose(ident.matrix(), np.eye(4), atol=1e-13)
    assert np.allclose(T.apply(x), _homogeneous_apply(T.matrix(), x), atol=1e-12)
    assert np.allclose(T.inverse().apply(T.apply(x)), x, atol=1e-12)
    assert np.allclose((T @ U).apply(x), T.apply(U.apply(x)), atol=1e-12)  # composition order: U first
    assert np.allclose(((T @ U) @ V).matrix(), (T @ (U @ V)).matrix(), atol=1e-12)
    assert np.allclose((T @ U).matrix(), T.matrix() @ U.matrix(), atol=1e-12)
    assert np.allclose(Rigid3.from_matrix(T.matrix()).matrix(), T.matrix(), atol=0)
    assert np.allclose(T.inverse().matrix(), np.linalg.inv(T.matrix()), atol=1e-12)


@settings(max_examples=30, **DETERMINISTIC)
@given(seeds)
def test_sim3_inverse_compose_apply(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T, U, V = _sim(rng), _sim(rng), _sim(rng)
    x = rng.uniform(-5, 5, (20, 3))
    for ident in (T.inverse() @ T, T @ T.inverse()):
        assert ident.s == pytest.approx(1.0, rel=1e-14)
        assert rotation_error(ident.R, np.eye(3)) < 1e-14
        assert np.allclose(ident.t, 0, atol=1e-12)
    scale_tol = 1e-12 * max(1.0, T.s, U.s, T.s * U.s, V.s)
    assert np.allclose(T.apply(x), _homogeneous_apply(T.matrix(), x), rtol=1e-13, atol=scale_tol)
    assert np.allclose(T.inverse().apply(T.apply(x)), x, atol=1e-11)
    assert np.allclose((T @ U).apply(x), T.apply(U.apply(x)), rtol=1e-12, atol=scale_tol)
    TU_V, T_UV = (T @ U) @ V, T @ (U @ V)
    assert TU_V.s == pytest.approx(T_UV.s, rel=1e-14)
    assert rotation_error(TU_V.R, T_UV.R) < 1e-14
    assert np.allclose(TU_V.t, T_UV.t, rtol=1e-12, atol=scale_tol)
    assert np.allclose((T @ U).matrix(), T.matrix() @ U.matrix(), rtol=1e-12, atol=scale_tol)
    assert np.allclose(T.inverse().matrix(), np.linalg.inv(T.matrix()), rtol=1e-10, atol=1e-10)


@settings(max_examples=30, **DETERMINISTIC)
@given(seeds)
def test_helpers_accept_every_kind(seed: int) -> None:
    rng = np.random.default_rng(seed)
    R, S = _rigid(rng), _sim(rng)
    x = rng.uniform(-5, 5, (10, 3))
    out = compose(R, R)
    assert isinstance(out, Rigid3)
    for a, b in ((R, S), (S, R), (S, S)):
        out = compose(a, b)
        assert isinstance(out, Sim3)
        assert np.allclose(out.apply(x), a.apply(b.apply(x)), rtol=1e-12, atol=1e-10)
    M = compose(S.matrix(), R)
    assert isinstance(M, np.ndarray) and M.shape == (4, 4)
    assert np.allclose(M, S.matrix() @ R.matrix(), rtol=1e-12, atol=1e-10)
    for T in (R, S, S.matrix()):
        inv = invert(T)
        assert type(inv) is type(T)
        back = compose(T, inv)
        assert np.allclose(back if isinstance(back, np.ndarray) else back.matrix(), np.eye(4), atol=1e-10)
        assert np.allclose(transform_points(inv, transform_points(T, x)), x, atol=1e-10)


@settings(max_examples=30, **DETERMINISTIC)
@given(seeds)
def test_sim3_from_matrix_round_trip(seed: int) -> None:
    S = _sim(np.random.default_rng(seed))
    back = sim3_from_matrix(S.matrix())
    assert back.s == pytest.approx(S.s, rel=1e-14)
    assert rotation_error(back.R, S.R) < 1e-14
    assert np.array_equal(back.t, S.t)


@pytest.mark.parametrize(
    ("M", "match"),
    [
        (np.diag([1.0, 1.0, -1.0, 1.0]), "det"),  # reflection
        (np.diag([0.0, 1.0, 1.0, 1.0]), "det"),  # singular
        (np.diag([1.0, 2.0, 1.0, 1.0]), "scaled rotation"),  # anisotropic scale
        (np.array([[1.0, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]), "scaled rotation"),  # shear
        (np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]), "bottom row"),
        (np.full((4, 4), np.nan), "NaN"),
        (np.eye(3), "shape"),
    ],
)
def test_sim3_from_matrix_rejects(M: np.ndarray, match: str) -> None:
    with pytest.raises(InputError, match=match):
        sim3_from_matrix(M)


def test_transform_points_shape_error() -> None:
    with pytest.raises(InputError):
        transform_points(Rigid3(), np.zeros((4, 2)))


def test_relative_pose_error() -> None:
    rng = np.random.default_rng(4)
    T = _rigid(rng)
    dR = np.array([[np.cos(0.1), -np.sin(0.1), 0], [np.sin(0.1), np.cos(0.1), 0], [0, 0, 1]])
    est = Rigid3(T.R @ dR, T.t + np.array([0.3, 0.0, 0.4]))
    rot, trans = relative_pose_error(est, T)
    assert rot == pytest.approx(0.1, abs=1e-14) and trans == pytest.approx(0.5, abs=1e-14)
    assert relative_pose_error(T, T) == (0.0, 0.0)
    # the translation error equals that of T_gt^-1 o T_est for rigid poses
    assert trans == pytest.approx(np.linalg.norm((T.inverse() @ est).t), abs=1e-12)


@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.parametrize("scale", [1e-150, 1e-103, 1e103, 1e150])
def test_sim3_from_matrix_extreme_scales_without_overflow(scale: float) -> None:
    M = np.eye(4)
    M[:3, :3] *= scale
    assert sim3_from_matrix(M).s == pytest.approx(scale, rel=1e-12)


def test_a_camera_pose_carried_by_a_similarity_keeps_what_the_camera_sees() -> None:
    """``Sim3.carry_pose``: the camera's centre moves with the similarity and its axes turn with it, so a point
    carried alongside keeps its direction in the camera (its depth scales by ``s``)."""
    rng = np.random.default_rng(3)
    S = _sim(rng)
    T_wc = _rigid(rng)
    carried = S.carry_pose(T_wc)
    np.testing.assert_allclose(carried.t, S.apply(T_wc.t[None])[0], atol=1e-12)
    X = rng.normal(size=(5, 3))
    before = T_wc.inverse().apply(X)
    after = carried.inverse().apply(S.apply(X))
    np.testing.assert_allclose(after, S.s * before, atol=1e-9)

"""The torch rotation functions agree with numpy, batch over (..., 3, 3) and have correct gradients."""

from __future__ import annotations

import numpy as np
import pytest
from geometry_testdata import DETERMINISTIC, rot_about, seeds
from hypothesis import given, settings
from hypothesis import strategies as st

import cadalign.geometry as geo

torch = pytest.importorskip("torch")
tr = pytest.importorskip("cadalign.geometry.torch_rotations")

lead_shapes = st.lists(st.integers(1, 3), min_size=0, max_size=3).map(tuple)


def _t(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(x))


@settings(max_examples=20, **DETERMINISTIC)
@given(seeds, lead_shapes)
def test_torch_matches_numpy_batched(seed: int, shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(seed)
    n = int(np.prod(shape, dtype=int))
    R = geo.random_rotation(rng, n).reshape(*shape, 3, 3)
    R2 = geo.random_rotation(rng, n).reshape(*shape, 3, 3)
    q = geo.matrix_to_quaternion(R)
    rv = geo.matrix_to_axis_angle(R)
    d6 = rng.standard_normal((*shape, 6))
    pairs = [
        (tr.matrix_to_quaternion(_t(R)), q),
        (tr.quaternion_to_matrix(_t(q)), geo.quaternion_to_matrix(q)),
        (tr.quaternion_to_matrix(_t(-3 * q)), geo.quaternion_to_matrix(q)),  # unnormalised, other sign
        (tr.axis_angle_to_matrix(_t(rv)), geo.axis_angle_to_matrix(rv)),
        (tr.rotation_6d_to_matrix(_t(d6)), geo.rotation_6d_to_matrix(d6)),
        (tr.matrix_to_rotation_6d(_t(R)), geo.matrix_to_rotation_6d(R)),
        (tr.geodesic_angle(_t(R), _t(R2)), geo.geodesic_angle(R, R2)),
    ]
    for got, want in pairs:
        assert got.dtype == torch.float64 and tuple(got.shape) == np.shape(want)
        assert np.allclose(got.numpy(), want, atol=1e-13, rtol=0)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 1e-5, 1e-3, 0.5, np.pi - 1e-3, np.pi - 1e-8])
def test_torch_numpy_agree_at_extremes(angle: float) -> None:
    R = rot_about(np.array([0.0, 0.6, 0.8]), angle)[None]
    rv = angle * np.array([[0.0, 0.6, 0.8]])
    assert np.allclose(tr.axis_angle_to_matrix(_t(rv)).numpy(), geo.axis_angle_to_matrix(rv), atol=1e-15)
    assert np.allclose(tr.matrix_to_quaternion(_t(R)).numpy(), geo.matrix_to_quaternion(R), atol=1e-15)
    ang = tr.geodesic_angle(torch.eye(3, dtype=torch.float64)[None], _t(R)).item()
    assert abs(ang - angle) < 1e-11  # eps clamp biases by at most eps / 2 = 5e-13


@pytest.mark.parametrize("axis", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, -0.6, 0.8]])
def test_torch_canonical_sign_matches_numpy_at_half_turn(axis: list[float]) -> None:
    k = np.array(axis)
    R = 2 * np.outer(k, k) - np.eye(3)  # exactly pi: w = 0, the tie-break decides
    got = tr.matrix_to_quaternion(_t(R)).numpy()
    want = geo.matrix_to_quaternion(R)
    assert np.allclose(got, want, atol=1e-15)
    assert np.array_equal(np.signbit(got), np.signbit(want))  # including the sign of zeros


def test_torch_float32_runs_and_is_close() -> None:
    rng = np.random.default_rng(2)
    d6 = rng.standard_normal((100, 6))
    R32 = tr.rotation_6d_to_matrix(torch.from_numpy(d6).float())
    assert R32.dtype == torch.float32
    assert np.allclose(R32.double().numpy(), geo.rotation_6d_to_matrix(d6), atol=1e-5)
    eye = torch.eye(3).expand(100, 3, 3)
    assert torch.all(tr.geodesic_angle(R32, R32) < 1e-3)
    assert torch.all(torch.isfinite(tr.geodesic_angle(eye, R32)))


def test_gradcheck_6d_to_matrix_float64() -> None:
    gen = torch.Generator().manual_seed(0)
    d6 = torch.randn(5, 6, dtype=torch.float64, generator=gen, requires_grad=True)
    assert torch.autograd.gradcheck(tr.rotation_6d_to_matrix, (d6,), eps=1e-6, atol=1e-8)
    assert torch.autograd.gradgradcheck(tr.rotation_6d_to_matrix, (d6,), eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("scale", [1e-5, 1e-2, 1.0, 3.0])
def test_gradcheck_other_maps(scale: float) -> None:
    gen = torch.Generator().manual_seed(1)
    rv = (scale * torch.randn(4, 3, dtype=torch.float64, generator=gen)).requires_grad_(True)
    assert torch.autograd.gradcheck(tr.axis_angle_to_matrix, (rv,), eps=1e-7, atol=1e-7)
    q = torch.randn(4, 4, dtype=torch.float64, generator=gen, requires_grad=True)
    assert torch.autograd.gradcheck(tr.quaternion_to_matrix, (q,), eps=1e-6, atol=1e-8)


def test_gradients_finite_at_identity() -> None:
    """Zero rotation vector and R1 == R2 are common in training; the gradients must not be NaN."""
    rv = torch.zeros(2, 3, dtype=torch.float64, requires_grad=True)
    tr.axis_angle_to_matrix(rv).sum().backward()
    assert torch.all(torch.isfinite(rv.grad))
    R = torch.eye(3, dtype=torch.float64).repeat(2, 1, 1).requires_grad_(True)
    tr.geodesic_angle(R, torch.eye(3, dtype=torch.float64)).sum().backward()
    assert torch.all(torch.isfinite(R.grad))

"""float32 vs float64: the same public function on float32 and float64 inputs agrees within a stated tolerance.

Each test's docstring states its tolerance and why. ``eps32 = 2**-23 ~ 1.19e-7`` is float32's relative
rounding. Where a function computes in float64 whatever it is given, only the rounding of the inputs differs
and the bound is a small multiple of ``eps32`` times the size of the inputs; where it computes in float32
(Open3D's BVH, the torch engine and rotations in float32, label fusion) the bound also covers the work done
in float32. (Projection/back-projection, Umeyama and BOP depth encoding are in test_numerics.py.)
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from cadalign.emulate.raycast_engines import BVHEngine, TorchEngine
from cadalign.fuse.semantic import bayes_update, clamped_log_probs, probs_from_labels
from cadalign.geometry import depth_to_points, geodesic_angle, kabsch, pixel_rays, umeyama
from cadalign.geometry import torch_rotations as tr
from cadalign.geometry.rotations import (
    matrix_to_quaternion,
    matrix_to_rotation_6d,
    quaternion_to_matrix,
    rotation_6d_to_matrix,
)
from cadalign.geometry.transforms import compose, invert, sim3_from_matrix, transform_points
from cadalign.metrics.depth import DepthEvalConfig, depth_errors, frame_depth_errors
from cadalign.types import Rigid3, Sim3

pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")
EPS32 = float(np.finfo(np.float32).eps)
K = np.array([[500.0, 0.0, 320.0], [0.0, 480.0, 240.0], [0.0, 0.0, 1.0]])


def _rotations(n: int, seed: int, near_pi: bool = False) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rv = rng.normal(size=(n, 3))
    rv /= np.linalg.norm(rv, axis=1, keepdims=True)
    angles = np.pi - rng.uniform(0, 1e-3, n) if near_pi else rng.uniform(0, np.pi, n)
    return Rotation.from_rotvec(rv * angles[:, None]).as_matrix()


# ------------------------------------------------------------------------------------- transforms, Sim(3)


@pytest.mark.parametrize("offset", [0.0, 1e3, 1e5])
def test_sim3_transform_points_and_compose_float32_inputs(offset: float) -> None:
    """Sim3/Rigid3 compute in float64 whatever they are given: the float32 path differs only by the input
    rounding. Tolerance: ``8 eps32 (s |x| + |t|)`` per coordinate (points 1 m across, ``offset`` m from the origin,
    rotated and scaled: each coordinate is a sum of three float32-rounded products plus t)."""
    rng = np.random.default_rng(0)
    R, s, t = _rotations(1, 1)[0], 2.5, np.array([offset, -offset / 2, 7.0])
    x = rng.uniform(-1, 1, (200, 3)) + offset
    T64 = Sim3(s, R, t)
    T32 = Sim3(np.float32(s), R.astype(np.float32), t.astype(np.float32))
    y64, y32 = T64.apply(x), T32.apply(x.astype(np.float32))
    assert y32.dtype == np.float64 and np.all(np.isfinite(y32))
    bound = 8 * EPS32 * (s * np.abs(x).max() + np.abs(t).max())
    assert np.abs(y32 - y64).max() <= bound
    # the functional API and a 4x4 matrix in float32
    M32 = np.eye(4, dtype=np.float32)
    M32[:3, :3], M32[:3, 3] = s * R, t
    S = sim3_from_matrix(M32)
    assert abs(S.s - s) <= 4 * EPS32 * s and geodesic_angle(S.R, R) <= 8 * EPS32
    np.testing.assert_allclose(transform_points(S, x.astype(np.float32)), y64, rtol=0, atol=2 * bound)
    round_trip = compose(invert(S), S)
    assert abs(round_trip.s - 1) <= 8 * EPS32 and geodesic_angle(round_trip.R, np.eye(3)) <= 8 * EPS32
    P = Rigid3(R.astype(np.float32), t.astype(np.float32))
    np.testing.assert_allclose(P.apply(x.astype(np.float32)), Rigid3(R, t).apply(x), rtol=0,
                               atol=8 * EPS32 * (np.abs(x).max() + np.abs(t).max()))


def test_umeyama_and_kabsch_weighted_float32_inputs() -> None:
    """Weighted Umeyama/Kabsch on float32 points (2 m spread, 50 m from the origin) and weights: the SVD is in
    float64, so the estimate moves only by the input rounding. Tolerance: rotation and relative scale within
    ``100 eps32 (1 + offset / spread)`` (the centring turns the absolute rounding at 50 m into a relative error
    at the 2 m spread; x100 covers the conditioning of the cross-covariance of 40 random points)."""
    rng = np.random.default_rng(3)
    src = rng.uniform(-1, 1, (40, 3)) + 50.0
    R, s, t = _rotations(1, 4)[0], 0.8, np.array([1.0, 2.0, -3.0])
    dst = s * src @ R.T + t
    w = rng.uniform(0.1, 1.0, 40)
    rel = 100 * EPS32 * (1 + 50.0 / 2.0)
    a, b = umeyama(src, dst, weights=w), umeyama(src.astype(np.float32), dst.astype(np.float32),
                                                 weights=w.astype(np.float32))
    assert abs(a.s - b.s) <= rel * s and geodesic_angle(a.R, b.R) <= rel
    ka, kb = kabsch(src, src @ R.T + t), kabsch(src.astype(np.float32), (src @ R.T + t).astype(np.float32))
    assert geodesic_angle(ka.R, kb.R) <= rel and np.abs(ka.t - kb.t).max() <= rel * 50.0


# --------------------------------------------------------------------------------------------- rotations


@pytest.mark.parametrize("near_pi", [False, True])
def test_numpy_rotation_conversions_float32_inputs(near_pi: bool) -> None:
    """quaternion <-> matrix <-> 6D on float32 inputs, including angles within 1e-3 rad of pi (where the
    quaternion's scalar part vanishes). Tolerance: ``16 eps32`` on every matrix entry and ``16 eps32`` rad
    on the round-trip angle: the conversions are a few float products of unit-sized values."""
    R = _rotations(300, 7, near_pi)
    q64, q32 = matrix_to_quaternion(R), matrix_to_quaternion(R.astype(np.float32))
    assert np.all(np.isfinite(q32))
    assert np.abs(np.abs((q32 * q64).sum(-1)) - 1).max() <= 16 * EPS32  # same rotation (q ~ -q)
    assert np.abs(quaternion_to_matrix(q32.astype(np.float32)) - R).max() <= 16 * EPS32
    d6 = matrix_to_rotation_6d(R)
    assert np.abs(rotation_6d_to_matrix(d6.astype(np.float32)) - rotation_6d_to_matrix(d6)).max() <= 16 * EPS32
    assert geodesic_angle(quaternion_to_matrix(q32), R).max() <= 16 * EPS32


@pytest.mark.parametrize("near_pi", [False, True])
def test_torch_rotations_float32_vs_float64(near_pi: bool) -> None:
    """The pose head's torch rotations in float32 (what the network runs in) vs float64: 6D -> matrix,
    quaternion -> matrix, axis-angle -> matrix and the geodesic angle (``atan2``, not ``acos``: accurate near 0
    and pi). Tolerance: ``32 eps32`` per matrix entry; the angle ``64 eps32`` rad absolute (an ``acos``
    would lose ~``sqrt(eps32)`` = 3e-4 rad near 0, which this bound rejects)."""
    R = torch.as_tensor(_rotations(300, 11, near_pi))
    d6 = tr.matrix_to_rotation_6d(R)
    q = tr.matrix_to_quaternion(R)
    rv = torch.as_tensor(Rotation.from_matrix(R.numpy()).as_rotvec())
    for fn, x in ((tr.rotation_6d_to_matrix, d6), (tr.quaternion_to_matrix, q), (tr.axis_angle_to_matrix, rv)):
        m64, m32 = fn(x), fn(x.float())
        assert m32.dtype == torch.float32 and torch.isfinite(m32).all()
        assert (m32.double() - m64).abs().max().item() <= 32 * EPS32, fn.__name__
    small = torch.as_tensor(Rotation.from_rotvec(np.outer(np.geomspace(1e-6, 1e-2, 20), [0.0, 0.6, 0.8])).as_matrix())
    eye = torch.eye(3, dtype=torch.float64).expand(20, 3, 3)
    for Ra, Rb in ((R, R.flip(0)), (eye, small)):
        a64, a32 = tr.geodesic_angle(Ra, Rb), tr.geodesic_angle(Ra.float(), Rb.float())
        assert (a32.double() - a64).abs().max().item() <= 64 * EPS32


# ------------------------------------------------------------------------------------------ ray casting


def _mesh_and_rays(offset: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A 2 m box of 12 triangles ``offset`` m from the origin, and 2000 rays from 4 m away at it."""
    c = np.array([offset, offset / 2, 0.0])
    v = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) + c
    f = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    rng = np.random.default_rng(5)
    o = c + np.array([4.0, -3.0, 2.5])
    d = (c + rng.uniform(-1.2, 1.2, (2000, 3))) - o
    return v, f, np.broadcast_to(o, d.shape).copy(), d


@pytest.mark.parametrize("offset", [0.0, 1e5])
def test_raycast_engines_float32_vs_float64(offset: float) -> None:
    """Both ray-cast engines, float32 vs float64 (the torch engine's ``dtype``, and float32 input arrays), on a box
    ``offset`` m from the origin (1e5: a UTM-like world; both engines shift to the mesh centre first, so
    float32 keeps millimetre precision there). Tolerance: the same rays hit (except within ``1e-4`` of an edge,
    at most 1 %) and ranges agree within ``8 eps32 * 10 m`` = 9.5e-6 m (float32 Möller-Trumbore / Embree on
    coordinates up to ~5 m from the centre, a few roundings each; the 1e5 m offset itself is subtracted in float64;
    measured 7.7e-7 m). Float32 *inputs*
    at 1e5 m are already rounded by up to 4 mm, so at that offset the inputs stay float64 and only the engines'
    own arithmetic is compared."""
    v, f, o, d = _mesh_and_rays(offset)
    ref = TorchEngine(v, f).cast(o, d)
    assert ref.hit.mean() > 0.5
    vin, oin, din = (v, o, d) if offset else (v.astype(np.float32), o.astype(np.float32), d.astype(np.float32))
    tol = 8 * EPS32 * 10.0
    for hits in (TorchEngine(vin, f, dtype="float32").cast(oin, din), BVHEngine(vin, f).cast(oin, din),
                 TorchEngine(vin, f).cast(oin, din)):
        assert (hits.hit == ref.hit).mean() >= 0.99
        both = hits.hit & ref.hit
        assert np.abs(hits.range_m[both] - ref.range_m[both]).max() <= tol
        same_face = both & (hits.face == ref.face)
        assert same_face.sum() >= 0.99 * both.sum()
        assert np.abs(hits.bary[same_face] - ref.bary[same_face]).max() <= 1e-4


# ------------------------------------------------------------------------------------- depth and metrics


def test_depth_to_points_and_pixel_rays_float32() -> None:
    """A float32 depth image (what networks and BOP decoding give) back-projects like its float64 copy.
    Tolerance: ``4 eps32 |P|`` per coordinate: only the depth's rounding differs (rays are float64)."""
    d = np.random.default_rng(2).uniform(0.3, 40.0, (48, 64))
    d[3, 4], d[5, 6] = 0.0, np.nan
    P64, v64 = depth_to_points(K, d)
    P32, v32 = depth_to_points(K.astype(np.float32), d.astype(np.float32))
    assert np.array_equal(v32, v64) and v64.sum() == d.size - 2
    assert np.abs(P32[v32] - P64[v64]).max() <= 4 * EPS32 * np.abs(P64[v64]).max()
    assert np.abs(pixel_rays(K.astype(np.float32), 64, 48, True) - pixel_rays(K, 64, 48, True)).max() <= 4 * EPS32


def test_depth_metrics_float32_vs_float64() -> None:
    """The Eigen depth metrics of float32 prediction/truth vs float64: computed in float64, so they differ by
    the input rounding. Tolerance: relative errors (abs_rel, rmse_log) within ``8 eps32``, rmse and sq_rel within
    ``8 eps32`` relative; the delta thresholds count the same pixels (no ratio within ``eps32`` of 1.25^k)."""
    rng = np.random.default_rng(4)
    gt = rng.uniform(0.5, 20.0, (60, 80))
    pred = gt * np.exp(rng.normal(0, 0.2, gt.shape))
    ratio = np.maximum(pred / gt, gt / pred)
    for k in (1, 2, 3):  # keep pixels away from the delta thresholds
        pred = np.where(np.abs(ratio - 1.25**k) < 1e-4, gt, pred)
    e64 = depth_errors(pred, gt)
    e32 = depth_errors(pred.astype(np.float32), gt.astype(np.float32))
    for k, v in e64.items():
        assert abs(e32[k] - v) <= 8 * EPS32 * max(abs(v), 1e-3), k
    cfg = DepthEvalConfig()
    gt_img = gt.copy()
    gt_img[gt_img > cfg.max_depth_m - 1e-3] = 0.0  # no pixel at the cap's edge
    f64, n64 = frame_depth_errors(pred, gt_img, cfg)
    f32, n32 = frame_depth_errors(pred.astype(np.float32), gt_img.astype(np.float32), cfg)
    assert n32 == n64 > 1000
    assert all(abs(f32[k] - f64[k]) <= 8 * EPS32 * max(abs(f64[k]), 1e-3) for k in f64)


# -------------------------------------------------------------------------------------------- label fusion


def _reference_fusion(obs_log_probs: np.ndarray, log_floor: float) -> np.ndarray:
    """The recursive Bayes update of :func:`bayes_update` in float64 (the definition, not the fast path)."""
    post = np.zeros(obs_log_probs.shape[1:], dtype=np.float64)
    for obs in obs_log_probs:
        post = post + obs
        post = np.maximum(post - post.max(1, keepdims=True), log_floor)
    return post


def test_label_fusion_float32_over_a_long_sequence_matches_float64() -> None:
    """2000 noisy observations of 500 voxels x 4 classes fused in float32 (the map's storage) vs the float64
    recursion. Each update adds about one rounding of a value in ``[log_floor, 0]`` with a random sign, and the
    floor/max renormalise stop the error from growing without bound: tolerance
    ``sqrt(n_updates) * 2 eps32 |log_floor|`` = 2.1e-4 (a random walk of roundings; measured 4.8e-6; the
    linear worst case would be 0.0095), and the fused labels (argmax) are the same
    wherever the float64 top two classes differ by more than that tolerance. float64 and float32 class
    probabilities give the same clamped log-probabilities within ``eps32 |log min_prob|``."""
    n_steps, n_vox, n_cls, log_floor, min_prob = 2000, 500, 4, -20.0, 1e-4
    rng = np.random.default_rng(9)
    truth = rng.integers(0, n_cls, n_vox)
    labels = np.where(rng.random((n_steps, n_vox)) < 0.4, rng.integers(0, n_cls, (n_steps, n_vox)), truth)
    probs = np.stack([probs_from_labels(lab[None], n_cls, 0.7)[:, 0].T for lab in labels])  # (S, N, C)
    probs = probs * rng.uniform(0.9, 1.1, probs.shape)
    obs64 = np.log(np.clip(probs.astype(np.float64), min_prob, 1.0))
    obs32 = np.stack([clamped_log_probs(p, min_prob) for p in probs])
    obs32_from64 = np.stack([clamped_log_probs(p.astype(np.float64), min_prob) for p in probs])
    assert obs32.dtype == np.float32 and np.array_equal(obs32, obs32_from64)
    assert np.abs(obs32 - obs64).max() <= EPS32 * abs(np.log(min_prob))
    post32 = np.zeros((n_vox, n_cls), dtype=np.float32)
    for obs in obs32:
        post32 = bayes_update(post32, obs, log_floor)
    post64 = _reference_fusion(obs64, log_floor)
    tol = np.sqrt(n_steps) * 2 * EPS32 * abs(log_floor)
    assert post32.dtype == np.float32 and np.all(np.isfinite(post32))
    assert np.abs(post32 - post64).max() <= tol
    top2 = np.sort(post64, 1)[:, -2:]
    clear = top2[:, 1] - top2[:, 0] > tol
    assert clear.mean() > 0.9
    assert np.array_equal(post32.argmax(1)[clear], post64.argmax(1)[clear])
    assert (post64.argmax(1) == truth).mean() > 0.99

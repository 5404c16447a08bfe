"""Edge alignment: contour samples sit half a pixel outside the near pixels, the 1-D edge search finds a
sub-pixel step edge of either contrast, the robust fit recovers a known motion despite outliers, and the
whole alignment takes perturbed cameras of a rendered scene back to the true ones (and leaves them alone
when the images hold no edges)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from cadalign.align.edge_refine import (
    EdgeRefineConfig,
    contour_samples,
    edge_align_frames,
    fit_correction,
    moved_camera,
    search_edges,
)
from cadalign.raycast.core import RaycastRenderer, RenderMesh
from cadalign.types import Camera, Rigid3, Sim3

CFG = EdgeRefineConfig()


def _look_at(eye: np.ndarray, target: np.ndarray) -> Rigid3:
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return Rigid3(np.stack([x, np.cross(z, x), z], axis=1), eye)


def _turn(rotvec: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(rotvec).as_matrix()


def test_contour_samples_of_a_square_lie_half_a_pixel_outside_with_outward_normals() -> None:
    depth = np.zeros((40, 50), dtype=np.float32)
    depth[5:25, 10:30] = 2.0
    rays = np.dstack([np.zeros((40, 50, 2)), np.ones((40, 50))]).astype(np.float32)
    X, uv, n = contour_samples(depth, rays, np.where(depth > 0, depth, np.inf), EdgeRefineConfig(point_step=1))
    assert len(X) > 60 and np.allclose(X[:, 2], 2.0)
    left = np.isclose(uv[:, 0], 9.5)
    right = np.isclose(uv[:, 0], 29.5)
    top = np.isclose(uv[:, 1], 4.5)
    assert left.sum() >= 18 and right.sum() >= 18 and top.sum() >= 18
    mid = (uv[:, 1] > 7) & (uv[:, 1] < 22)  # away from the corners the normal is exact
    assert np.allclose(n[left & mid], [-1, 0], atol=1e-6) and np.allclose(n[right & mid], [1, 0], atol=1e-6)
    # a step of less than ``depth_jump`` is no contour; open water beyond it is
    depth[5:25, 10:20] = 2.05
    X2, uv2, _ = contour_samples(depth, rays, np.where(depth > 0, depth, np.inf), EdgeRefineConfig(point_step=1))
    assert not np.any(np.isclose(uv2[:, 0], 19.5) & (uv2[:, 1] > 7) & (uv2[:, 1] < 22))
    assert contour_samples(np.zeros((8, 8), np.float32), rays[:8, :8], np.full((8, 8), np.inf), CFG)[0].shape == (0, 3)


def test_contour_normals_are_the_whole_image_sobel_gradient_of_inverse_depth() -> None:
    """The normals are read from a Sobel filter at the contour pixels only; they must be the whole-image
    filter's (cv2, reflected border), bit for bit, including at the image border."""
    import cv2

    rng = np.random.default_rng(3)
    depth = (2.0 + rng.random((30, 40))).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0.0  # open water: many contours, some on the border
    cols, rows = np.meshgrid(np.arange(40), np.arange(30))
    rays = np.dstack([cols, rows, np.ones((30, 40))]).astype(np.float32)  # X = (column, row, 1): the pixel
    X, _, n = contour_samples(depth, rays, np.where(depth > 0, 1.0, np.inf), EdgeRefineConfig(point_step=1))
    z = np.where(depth > 0, depth, np.inf).astype(np.float64)
    inv = np.where(np.isfinite(z), 1.0 / z, 0.0)
    g = -np.stack([cv2.Sobel(inv, cv2.CV_64F, 1, 0, ksize=3), cv2.Sobel(inv, cv2.CV_64F, 0, 1, ksize=3)], axis=-1)
    near = X[:, :2].astype(int)
    assert len(X) > 100 and (near[:, 0] == 0).any() and (near[:, 1] == 29).any()
    ref = g[near[:, 1], near[:, 0]]
    ref = ref / np.linalg.norm(ref, axis=1, keepdims=True)
    assert np.array_equal(n, ref)


def _step_image(edge_x: float, dark_left: bool, blur: float = 0.0) -> np.ndarray:
    """A vertical step edge at x = edge_x (pixel centres at integers), by area coverage, optionally blurred."""
    import cv2

    x = np.arange(64, dtype=np.float64)
    cover = np.clip(x + 0.5 - edge_x, 0.0, 1.0)
    row = 60.0 + 120.0 * (cover if dark_left else 1.0 - cover)
    img = np.repeat(row[None], 32, axis=0).astype(np.float32)
    return cv2.GaussianBlur(img, (0, 0), blur) if blur else img


TOL = {0.0: 0.21, 0.8: 0.14, 1.5: 0.08}  # px; a sharp step's mixed pixel biases the derivative's peak most


@settings(max_examples=25, deadline=None)
@given(shift=st.floats(-2.4, 2.4), dark_left=st.booleans(), blur=st.sampled_from(sorted(TOL)))
def test_edge_search_finds_a_subpixel_step_of_either_contrast(shift: float, dark_left: bool, blur: float) -> None:
    predicted = 30.3
    img = _step_image(predicted + shift, dark_left, blur)
    uv = np.array([[predicted, 10.0], [predicted, 20.0]])
    off = search_edges(img, uv, np.array([[1.0, 0.0], [1.0, 0.0]]), CFG)
    assert np.all(np.abs(off - shift) < TOL[blur]), (off, shift)


@pytest.mark.parametrize("blur", sorted(TOL))
def test_edge_search_errors_average_out_over_edge_positions(blur: float) -> None:
    """The fit rests on thousands of edges at all sub-pixel phases: their mean error must be ~0."""
    shifts = np.linspace(-2.0, 2.0, 81)
    uv, n = np.array([[30.3, 10.0]]), np.array([[1.0, 0.0]])
    err = [search_edges(_step_image(30.3 + d, dark, blur), uv, n, CFG)[0] - d for d in shifts for dark in (0, 1)]
    assert abs(np.mean(err)) < 0.02


def test_edge_search_reports_nothing_without_an_edge_or_beyond_its_range() -> None:
    flat = np.full((32, 64), 90.0, np.float32)
    uv, n = np.array([[30.0, 10.0]]), np.array([[1.0, 0.0]])
    assert np.isnan(search_edges(flat, uv, n, CFG)).all()
    assert np.isnan(search_edges(_step_image(30.0 + 6.0, True), uv, n, CFG)).all()  # 6 px away, range 3 px
    # an edge just inside the range's end has no neighbour beyond it for the sub-pixel peak: nothing either
    assert np.isnan(search_edges(_step_image(30.0 + CFG.search_px + 0.25, True), uv, n, CFG)).all()
    assert np.isfinite(search_edges(_step_image(30.0 + CFG.search_px - 1.0, True), uv, n, CFG)).all()
    assert search_edges(flat, np.zeros((0, 2)), np.zeros((0, 2)), CFG).shape == (0,)  # no contour samples
    tiny = EdgeRefineConfig(search_px=0.4)  # no far half of the range to read the contrast's sign from
    assert np.isnan(search_edges(_step_image(30.2, True), uv, n, tiny)).all()


def test_robust_fit_recovers_a_known_motion_despite_gross_outliers() -> None:
    rng = np.random.default_rng(3)
    J = rng.normal(size=(2000, 6)) * np.r_[np.full(3, 800.0), np.full(3, 60.0)]
    xi = np.r_[np.radians([0.05, -0.08, 0.02]), 0.004, -0.002, 0.006]
    r = -J @ xi + rng.normal(0, 0.1, 2000)
    r[:300] = rng.uniform(-3, 3, 300)  # wrong edges
    est, w = fit_correction([(J[:1000], r[:1000]), (J[1000:], r[1000:])], tukey_px=1.5)
    assert np.allclose(est[:3], xi[:3], atol=np.radians(0.003)) and np.allclose(est[3:], xi[3:], atol=3e-4)
    assert (w[300:] > 0).mean() > 0.97


def test_prior_holds_what_the_edges_leave_free_and_yields_to_what_they_fix() -> None:
    """A direction the edges do not see (a weak column: a shift that trades with a turn) stays near the start
    under the prior, and goes back to it from a correction already made; the well-seen ones follow the data."""
    rng = np.random.default_rng(5)
    J = rng.normal(size=(3000, 6)) * np.r_[np.full(3, 800.0), np.full(3, 60.0)]
    J[:, 4] = 0.002 * rng.normal(size=3000)  # y shift: hardly seen
    xi = np.r_[np.radians([0.05, -0.08, 0.02]), 0.004, 0.0, 0.006]
    r = -J @ xi + rng.normal(0, 0.15, 3000)
    r += 0.002 * rng.normal(size=3000) * 8.0  # noise along the weak column: alone it would pull y by ~cm
    free, _ = fit_correction([(J, r)], tukey_px=1.5)
    prec = (5.0 / np.r_[np.full(3, np.radians(0.05)), np.full(3, 0.01)]) ** 2
    held, _ = fit_correction([(J, r)], tukey_px=1.5, prior=(np.zeros(6), prec))
    back, _ = fit_correction([(J, r)], tukey_px=1.5, prior=(np.r_[0, 0, 0, 0, 0.02, 0], prec))
    assert abs(free[4]) > 0.005  # without the prior the noise moves the blind direction
    assert abs(held[4]) < 0.2 * abs(free[4]) and abs(back[4] + 0.02) < 0.004  # held, and taken back
    for est in (held, back):  # the others still follow the edges
        assert np.allclose(est[[0, 1, 2]], xi[[0, 1, 2]], atol=np.radians(0.004))
        assert np.allclose(est[[3, 5]], xi[[3, 5]], atol=5e-4)


def _boxes_scene() -> tuple[RaycastRenderer, np.ndarray, np.ndarray]:
    """A renderer of three boxes (320x240), their centre and their corners."""
    meshes = []
    for k, (size, pos) in enumerate((([2.0, 1.2, 1.0], [0, 0, 0.5]), ([0.4, 0.4, 0.8], [0.6, -0.2, 1.4]),
                                     ([0.3, 1.6, 0.3], [-0.7, 0.3, 1.15]))):
        b = trimesh.creation.box(extents=size)
        meshes.append(RenderMesh(np.asarray(b.vertices) + pos, np.asarray(b.faces), k + 1, 1))
    K = np.array([[260.0, 0, 160], [0, 260.0, 120], [0, 0, 1]])
    corners = np.concatenate([m.vertices_m for m in meshes])
    return RaycastRenderer(meshes, Camera(K, 320, 240)), corners.mean(axis=0), corners


def _shaded(renderer: RaycastRenderer, T_wc: Rigid3) -> np.ndarray:
    """The scene as a camera would see it: faces shaded by their normal, open water dark."""
    import cv2

    f = renderer.render(T_wc, with_full_masks=False)
    light = np.array([0.3, -0.5, -0.8]) / np.linalg.norm([0.3, -0.5, -0.8])
    img = np.where(f.depth_m > 0, 70.0 + 150.0 * np.abs(f.normals_cam @ (T_wc.R.T @ light)), 25.0)
    # supersampling stand-in: a slight blur, as a lens and the water give
    return cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.7)


@pytest.mark.parametrize("per_frame", [False, True])
def test_edge_alignment_takes_perturbed_cameras_back_to_the_images(per_frame: bool) -> None:
    renderer, centre, corners = _boxes_scene()
    truth = {f"{k:02d}.png": _look_at(centre + 5.0 * np.array([np.cos(a), np.sin(a), 0.45]), centre)
             for k, a in enumerate(np.linspace(0, 2 * np.pi, 6, endpoint=False))}
    images = {n: _shaded(renderer, T) for n, T in truth.items()}
    rng = np.random.default_rng(0)
    # the alignment's error: a similarity of the world (0.36 deg, 1.2 cm, 0.5 % scale) about the centre
    H = Sim3(1.005, _turn(np.radians([0.25, -0.15, 0.2])), np.zeros(3))
    H = Sim3(H.s, H.R, centre - H.s * (H.R @ centre) + np.array([0.01, -0.006, 0.004]))
    start = {}
    for n, T in truth.items():
        own = Rigid3(_turn(np.radians(rng.normal(0, 0.08, 3))), rng.normal(0, 0.003, 3)) if per_frame else \
            Rigid3.identity()
        start[n] = own @ moved_camera(H, T)

    def err(poses: dict[str, Rigid3]) -> tuple[float, float, float]:
        """Largest rotation (deg), camera-centre (m) and image (px) error over the frames; the image error is
        the largest displacement of the boxes' corners from where the true camera sees them."""
        d = [truth[n].inverse() @ poses[n] for n in truth]
        turn = max(np.degrees(np.arccos(np.clip((np.trace(x.R) - 1) / 2, -1, 1))) for x in d)
        shift = max(np.linalg.norm(truth[n].t - poses[n].t) for n in truth)

        def uv(T: Rigid3) -> np.ndarray:
            Xc = T.inverse().apply(corners)
            return renderer.camera.K[0, 0] * Xc[:, :2] / Xc[:, 2:]

        return float(turn), float(shift), float(max(np.abs(uv(poses[n]) - uv(truth[n])).max() for n in truth))

    cfg = EdgeRefineConfig(frames=6, per_frame=per_frame, min_edges=200, min_frame_edges=100)  # a small scene
    out, info, summary = edge_align_frames(start, lambda n: renderer, lambda n: images[n], centre, cfg)
    (r0, t0, p0), (r1, t1, p1) = err(start), err(out)
    assert summary["shared"]["applied"] and r0 > 0.25 and p0 > 0.5
    if not per_frame:  # one shared similarity: recovered
        assert abs(summary["shared"]["scale"] * 1.005 - 1) < 0.002  # 0.5 % error -> under 0.2 %
        assert r1 < 0.3 * r0 and t1 < 0.3 * t0 and p1 < 0.2, (r0, t0, p0, r1, t1, p1)
    else:
        # each frame alone: the image fits to a fraction of a pixel; its 3-D pose keeps some of the
        # rotation/translation trade-off of a single view of a few boxes
        assert summary["frames_refined"] >= 5 and sum(v["applied"] for v in info.values()) == summary["frames_refined"]
        assert p1 < 0.4 * p0 and p1 < 0.4, (p0, p1)


def test_edge_alignment_leaves_cameras_alone_without_image_edges() -> None:
    renderer, centre, _ = _boxes_scene()
    poses = {f"{k}": _look_at(centre + 5.0 * np.array([np.cos(a), np.sin(a), 0.45]), centre)
             for k, a in enumerate((0.0, 2.0, 4.0))}
    blank = np.full((240, 320), 40.0, np.float32)
    out, info, summary = edge_align_frames(poses, lambda n: renderer, lambda n: blank, centre, CFG)
    assert not summary["shared"]["applied"] and summary["frames_refined"] == 0
    for n, T in poses.items():
        assert np.array_equal(out[n].matrix(), T.matrix()) and not info[n]["applied"]
    off, _, s_off = edge_align_frames(poses, lambda n: renderer, lambda n: blank, centre,
                                      EdgeRefineConfig(enabled=False))
    assert off == poses and s_off["applied"] is False

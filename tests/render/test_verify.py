"""Image verification: on rendered views of an asymmetric object over a cluttered background, the right placement
has a clear edge lift and no free-space violations, a turned or shifted one has neither, the right one is chosen
even when the cloud ranked it second, and the decision refuses weak, contradicted or ambiguous evidence."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from cadalign.align.verify.core import (
    FreeSpaceRays,
    HypothesisEvidence,
    VerifyConfig,
    View,
    decide,
    verify,
)
from cadalign.raycast.core import RaycastRenderer, RenderMesh, pixel_rays_cam
from cadalign.types import Camera, Rigid3, Sim3

CAM = Camera(np.array([[200.0, 0, 80], [0, 200.0, 60], [0, 0, 1]]), 160, 120)


def _look_at(eye: np.ndarray, target: np.ndarray) -> Rigid3:
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return Rigid3(np.stack([x, np.cross(z, x), z], axis=1), eye)


def _object() -> RenderMesh:
    """An L of two boxes (no symmetry), standing on z = 0."""
    a = trimesh.creation.box((1.2, 0.4, 0.5))
    a.apply_translation((0.0, 0.0, 0.25))
    b = trimesh.creation.box((0.4, 0.8, 0.9))
    b.apply_translation((0.4, 0.6, 0.45))
    m = trimesh.util.concatenate([a, b])
    return RenderMesh(np.asarray(m.vertices), np.asarray(m.faces), 1, 1)


def _ground() -> RenderMesh:
    g = trimesh.creation.box((8.0, 8.0, 0.02))
    g.apply_translation((0.0, 0.0, -0.011))
    return RenderMesh(np.asarray(g.vertices), np.asarray(g.faces), 0, 0)


def _clutter(rng: np.random.Generator) -> np.ndarray:
    """A background image of random rectangles: plenty of edges that are not the object's."""
    img = np.full((CAM.height, CAM.width), 110.0)
    for _ in range(60):
        x0, y0 = rng.integers(0, CAM.width), rng.integers(0, CAM.height)
        img[y0:y0 + rng.integers(3, 25), x0:x0 + rng.integers(3, 25)] = rng.uniform(40, 200)
    return img


@pytest.fixture(scope="module")
def scene() -> tuple[list[View], RenderMesh, FreeSpaceRays]:
    """Six views round the object (SfM frame = world), grey images, and free-space observations."""
    rng = np.random.default_rng(0)
    obj, ground = _object(), _ground()
    both = RaycastRenderer([obj, ground], CAM)
    views, origins, points = [], [], []
    cloud = np.concatenate([rng.uniform([-3, -3, 0], [3, 3, 0], (400, 3)),
                            trimesh.sample.sample_surface(trimesh.Trimesh(obj.vertices_m, obj.faces), 300,
                                                          seed=0)[0]])
    import open3d as o3d

    from cadalign.align.verify.evidence import cad_scene, free_space_evidence

    scene_obj, origin = cad_scene([obj])
    for k, az in enumerate(np.radians(np.arange(0, 360, 60) + 15)):
        T = _look_at(np.array([3.5 * np.cos(az), 3.5 * np.sin(az), 2.0]), np.array([0.2, 0.2, 0.3]))
        f = both.render(T, with_full_masks=False)
        shade = 60 + 120 * np.abs(f.normals_cam[..., 0])  # faces differ in brightness, as lit surfaces do
        gray = np.where(f.instance > 0, shade, _clutter(rng)).astype(np.float32)
        views.append(View(f"{k:02d}.png", CAM, pixel_rays_cam(CAM), gray, T.R.T, T.t))
        # a point is observed from here when nothing hides it (the true geometry)
        d = cloud - T.t
        dist = np.linalg.norm(d, axis=1)
        o = np.broadcast_to(T.t - origin, d.shape)
        t = scene_obj.cast_rays(o3d.core.Tensor(np.concatenate([o, d / dist[:, None]], 1).astype(np.float32)))
        t = t["t_hit"].numpy()
        seen = t >= dist - 1e-3
        origins.append(np.repeat(T.t[None], seen.sum(), 0))
        points.append(cloud[seen])
    rays = FreeSpaceRays(np.concatenate(origins), np.concatenate(points))
    assert free_space_evidence(*cad_scene([obj]), rays, Sim3.identity(), 0.02, 0.01)[1] == 0
    return views, obj, rays


def _turn_z(deg: float, about: np.ndarray) -> Sim3:
    a = np.radians(deg)
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    return Sim3(1.0, R, about - R @ about)


CFG = VerifyConfig(min_samples=100, min_free_rays=20)


def test_the_right_placement_wins_even_when_the_cloud_ranked_it_second(scene) -> None:
    views, obj, rays = scene
    c = obj.vertices_m.mean(axis=0)
    hyps = [_turn_z(180, c), Sim3.identity(), Sim3(1.0, np.eye(3), np.array([0.3, 0.0, 0.0]))]
    ver = verify(views, [obj], hyps, [0.9, 0.8, 0.7], rays, CFG, inlier_m=0.02)
    ev = {e.index: e for e in ver.evidence}
    assert ver.outcome == "ok" and ver.chosen == 1, ver
    assert ev[1].edge > 0.5 and ev[1].free_violation < 0.02
    assert ev[0].edge < 0.3 and ev[2].edge < 0.3  # clutter gives the wrong ones chance hits, not a lift
    assert ev[0].free_violation > 0.05 or ev[2].free_violation > 0.05
    assert ver.margin is not None and ver.margin > 0.5 and ver.runner_up in (0, 2)


def test_a_wrong_placement_alone_is_refused(scene) -> None:
    views, obj, rays = scene
    ver = verify(views, [obj], [Sim3(1.0, np.eye(3), np.array([0.0, 0.5, 0.0]))], [0.9], rays, CFG, 0.02)
    assert ver.outcome in ("wrong", "uncertain") and ver.reasons and ver.fix
    assert ver.margin is None  # a single hypothesis has no runner-up


def test_a_mirrored_cad_is_refused(scene) -> None:
    views, obj, rays = scene
    mirrored = RenderMesh(obj.vertices_m * [1, -1, 1] + [0, 0.4, 0], obj.faces[:, ::-1], 1, 1)
    ver = verify(views, [mirrored], [Sim3.identity()], [0.9], rays, CFG, 0.02)
    assert ver.outcome != "ok", ver.evidence


def _ev(i: int, edge: float, free: float = 0.0, samples: int = 1000, same_as: int = -1) -> HypothesisEvidence:
    return HypothesisEvidence(i, 0.5, edge, 0.5, 0.3, samples, free, 500, edge * (1 - free), same_as)


def test_decide_outcomes() -> None:
    cfg = VerifyConfig()
    h = [Sim3.identity()] * 3
    assert decide([_ev(0, 0.6), _ev(1, 0.05)], h, cfg)[0] == "ok"
    assert decide([_ev(0, 0.02)], h, cfg)[0] == "wrong"
    assert decide([_ev(0, 0.6, free=0.5)], h, cfg)[0] == "wrong"
    assert decide([_ev(0, 0.2)], h, cfg)[0] == "uncertain"
    assert decide([_ev(0, 0.6, samples=10)], h, cfg)[0] == "uncertain"
    outcome, chosen, runner, margin, reasons = decide([_ev(0, 0.5), _ev(1, 0.45)], h, cfg)
    assert (outcome, chosen, runner) == ("uncertain", 0, 1) and margin == pytest.approx(0.1)
    assert "hypothesis 1" in reasons[0]
    # a look-alike (a symmetric structure's turn) is no rival; a person's choice needs no margin
    assert decide([_ev(0, 0.5), _ev(1, 0.5, same_as=0)], h, cfg)[0] == "ok"
    assert decide([_ev(0, 0.6), _ev(1, 0.55)], h, cfg, choice=1)[:2] == ("ok", 1)
    # a person's choice needs its own evidence: weak or contradicted evidence still refuses
    assert decide([_ev(0, 0.6), _ev(1, 0.2)], h, cfg, choice=1)[:2] == ("uncertain", 1)
    assert decide([_ev(0, 0.6), _ev(1, 0.6, free=0.5)], h, cfg, choice=1)[0] == "wrong"

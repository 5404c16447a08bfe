"""The lost survey's search (:mod:`cadalign.infer.track.survey`): six coloured boxes on a grey ground, a camera
looking down at 50 deg from 4 m up. After a turn of 90 deg out of view, the search over the ground finds the view
by the colours the tracker learned; and a search that finds two different views fitting alike refuses both."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from cadalign.geometry.rotations import axis_angle_to_matrix, geodesic_angle
from cadalign.infer.track.config import TrackerConfig
from cadalign.infer.track.edges import EdgeLevel, EdgeTrackConfig, as_gray
from cadalign.infer.track.survey import SurveyConfig, best_by_colour, ground_views
from cadalign.infer.track.tracker import StructureTracker
from cadalign.types import Camera, Rigid3

CAM = Camera(np.array([[260.0, 0, 160], [0, 260.0, 120], [0, 0, 1]]), 320, 240)
COLOURS = np.array([(90, 90, 90), (40, 90, 150), (200, 80, 40), (60, 170, 60), (210, 190, 40), (150, 60, 170),
                    (200, 200, 200)], np.float32)
"""The ground's grey (instance 0) and each box's colour."""
SURVEY = SurveyConfig(step_m=0.5, margin_m=1.0, yaw_step_deg=15.0, scale=0.125, fits=4)
TRACKER = TrackerConfig(edges=EdgeTrackConfig(levels=(EdgeLevel(0.5, 5, 5.0, 3.0), EdgeLevel(1.0, 4, 3.0, 1.5))),
                        restart_levels=(EdgeLevel(0.25, 8, 4.0, 3.0), EdgeLevel(0.5, 6, 5.0, 3.0),
                                        EdgeLevel(1.0, 4, 3.0, 1.5)),
                        orbit_step_deg=0.0, turn_step_deg=0.0, survey=SURVEY)
"""The boxes' tracker with no turned views: only the survey's search can regain a quarter turn."""


@pytest.fixture(scope="module")
def scene():
    """(meshes, render(T_world_from_cam) -> (gray, rgb)) of six boxes over 3 x 3 m."""
    import trimesh

    from cadalign.raycast.core import RaycastRenderer, RenderMesh

    rng = np.random.default_rng(3)
    meshes = []
    for i, p in enumerate([(-1.2, -1.0, 0.3), (1.0, -1.1, 0.5), (0.0, 0.2, 0.8), (-1.0, 1.1, 0.4), (1.2, 1.0, 0.25),
                           (0.3, -0.2, 1.6)]):
        b = trimesh.creation.box(extents=rng.uniform(0.3, 0.8, 3))
        b.apply_transform(trimesh.transformations.euler_matrix(0, 0, rng.uniform(0, np.pi)))
        b.apply_translation(p)
        meshes.append(RenderMesh(np.asarray(b.vertices), np.asarray(b.faces), i + 1, 1))
    renderer = RaycastRenderer(meshes, CAM)
    light = np.array([0.3, -0.5, -0.8]) / np.linalg.norm([0.3, -0.5, -0.8])

    def render(T_world_from_cam: Rigid3) -> tuple[np.ndarray, np.ndarray]:
        f = renderer.render(T_world_from_cam, with_full_masks=False)
        shade = np.where(f.instance > 0, 0.5 + 0.5 * np.abs(f.normals_cam @ (T_world_from_cam.R.T @ light)), 1.0)
        rgb = np.clip(COLOURS[f.instance] * shade[..., None], 0, 255).astype(np.uint8)
        return as_gray(rgb), rgb

    return meshes, render


def _down_view(eye: np.ndarray, heading_deg: float) -> Rigid3:
    """``T_world_from_cam`` at ``eye`` heading ``heading_deg`` (from +x towards +y), looking down 50 deg."""
    h, p = np.radians(heading_deg), np.radians(50.0)
    z = np.array([np.cos(h) * np.cos(p), np.sin(h) * np.cos(p), -np.sin(p)])
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return Rigid3(np.stack([x, np.cross(z, x), z], axis=1), eye)


FIRST = _down_view(np.array([-3.6, -0.5, 4.8]), 0.0)  # looking at the boxes along +x
TURNED = _down_view(np.array([0.45, -3.85, 4.78]), 90.0)  # a quarter turn later, from the -y side, 2 cm lower


def _err(A: Rigid3, B: Rigid3) -> tuple[float, float]:
    return float(np.linalg.norm(A.t - B.t)), float(np.degrees(geodesic_angle(A.R, B.R)))


def test_ground_views_keep_height_and_tilt_and_cover_heading_and_place() -> None:
    lo, hi = np.array([-1.5, -1.5, 0.0]), np.array([1.5, 1.5, 1.8])
    views = ground_views(FIRST, lo, hi, SURVEY)
    assert len(views) == (360 // 15) * 11 * 11  # -2.5 .. 2.5 m in 0.5 m steps
    tilt = [np.degrees(np.arccos(-T.R[2, 2])) for T in views]  # the optical axis from straight down
    np.testing.assert_allclose(tilt, np.degrees(np.arccos(-FIRST.R[2, 2])), atol=1e-9)
    np.testing.assert_allclose([T.t[2] for T in views], FIRST.t[2], atol=1e-9)
    assert abs(views[0].R[2, 0]) < 1e-12  # no roll: the image's x axis stays level
    assert min(_err(T, TURNED)[0] + _err(T, TURNED)[1] / 30 for T in views) < 0.6  # one within ~0.35 m, 7.5 deg
    up = Rigid3(axis_angle_to_matrix(np.array([np.pi / 2, 0.0, 0.0])), np.array([0.0, -5.0, 1.0]))  # looks level
    assert ground_views(up, lo, hi, SURVEY) == []


def test_the_learned_colours_rank_the_view_after_a_turn_first(scene) -> None:
    meshes, render = scene
    tr = StructureTracker(meshes, CAM, TRACKER)
    gray, rgb = render(FIRST)
    assert tr.step(gray, [("init", FIRST.inverse())], rgb).state == "ok" and tr.edges.region.ready
    lo = np.min([m.vertices_m.min(axis=0) for m in meshes], axis=0)
    hi = np.max([m.vertices_m.max(axis=0) for m in meshes], axis=0)
    gray, rgb = render(TURNED)
    best = best_by_colour(tr.edges, rgb, ground_views(FIRST, lo, hi, SURVEY), SURVEY)
    assert 1 <= len(best) <= SURVEY.fits
    assert all(_err(a, b)[0] >= SURVEY.apart_m or _err(a, b)[1] >= SURVEY.apart_deg
               for i, a in enumerate(best) for b in best[:i])
    t, r = _err(best[0], TURNED)
    assert t < 0.6 and r < 10, (t, r)


@pytest.mark.parametrize("survey", ["on", "off", "poor colours"])
def test_a_lost_survey_is_regained_after_a_quarter_turn_out_of_view(scene, survey: str) -> None:
    meshes, render = scene
    cfg = {"on": TRACKER, "off": replace(TRACKER, survey=replace(SURVEY, every=0)),
           "poor colours": replace(TRACKER, survey=replace(SURVEY, min_region=1.01))}[survey]  # above any support
    tr = StructureTracker(meshes, CAM, cfg)
    gray, rgb = render(FIRST)
    assert tr.step(gray, [("init", FIRST.inverse())], rgb).state == "ok"
    assert tr.step(gray, (), rgb).state == "ok"  # the track's first region support (the first frame taught them)
    black = np.zeros_like(rgb)
    assert tr.step(as_gray(black), (), black).state == "lost"  # out of view (a frame with no edges)
    gray, rgb = render(TURNED)
    s = tr.step(gray, (), rgb)
    if survey != "on":  # dead reckoning and the last pose are a quarter turn off: nothing else regains it
        assert s.state == "lost" and s.T_cam_from_world is None
        return
    assert s.state == "ok" and s.source.startswith("survey"), s
    t, r = _err(s.T_cam_from_world.inverse(), TURNED)
    assert t < 0.03 and r < 0.3, (t, r)  # about a pixel at 5 m


def _fake(t: tuple[float, float, float], support: float) -> SimpleNamespace:
    return SimpleNamespace(T_world_from_cam=Rigid3(np.eye(3), np.array(t)), support=support, instance_support={})


@pytest.mark.parametrize(("second", "unique", "taken"), [
    (((2.0, 0.0, 0.0), 0.68), True, False),  # another view 2 m away fits alike: refused
    (((2.0, 0.0, 0.0), 0.60), True, True),  # ... fits clearly worse: the best is taken
    (((0.2, 0.0, 0.0), 0.69), True, True),  # 0.2 m away: the same view
    (((2.0, 0.0, 0.0), 0.68), False, True),  # no uniqueness asked: the best is taken
])
def test_a_unique_search_refuses_two_views_that_fit_alike(scene, monkeypatch, second, unique: bool,
                                                          taken: bool) -> None:
    meshes, _ = scene
    tr = StructureTracker(meshes, CAM, TRACKER)
    fits = {"a": _fake((0.0, 0.0, 0.0), 0.70), "b": _fake(*second)}
    hyps = [(name, Rigid3(np.eye(3), np.array([float(i), 0.0, 0.0]))) for i, name in enumerate(fits)]
    monkeypatch.setattr(tr, "_search", lambda gray, T_wc: (fits["ab"[int(round(-T_wc.t[0]))]], 1))
    best, tried = tr._best_of(np.zeros((240, 320), np.float32), hyps, own=False, unique=unique)
    assert tried == 2
    assert (best is not None and best[1] == "a") if taken else best is None


def test_a_frame_without_the_structure_gives_no_view(scene) -> None:
    """Ground alone: no view explains its colours better with the boxes than without, so none is fitted."""
    meshes, render = scene
    tr = StructureTracker(meshes, CAM, TRACKER)
    gray, rgb = render(FIRST)
    assert tr.step(gray, [("init", FIRST.inverse())], rgb).state == "ok"
    lo = np.min([m.vertices_m.min(axis=0) for m in meshes], axis=0)
    hi = np.max([m.vertices_m.max(axis=0) for m in meshes], axis=0)
    ground = np.broadcast_to(COLOURS[0].astype(np.uint8), rgb.shape).copy()
    assert best_by_colour(tr.edges, ground, ground_views(FIRST, lo, hi, SURVEY), SURVEY) == []
    assert best_by_colour(tr.edges, rgb, ground_views(FIRST, lo, hi, SURVEY), SURVEY) != []



def test_silhouettes_of_many_views_are_the_renders_masks(scene) -> None:
    """One batched cast per chunk gives what a render per view gives (chunks smaller than the views: the seams)."""
    from cadalign.raycast.core import RaycastRenderer

    meshes, _ = scene
    small = Camera(np.array([[32.5, 0, 20], [0, 32.5, 15], [0, 0, 1]]), 40, 30)
    r = RaycastRenderer(meshes, small)
    views = [FIRST, TURNED, _down_view(np.array([3.0, 3.0, 4.0]), 225.0), _down_view(np.array([9.0, 9.0, 4.0]), 45.0)]
    sil = r.silhouettes(views, chunk=3)
    for T, s in zip(views, sil, strict=True):
        np.testing.assert_array_equal(s, r.render(T, with_full_masks=False).instance.ravel() > 0)
    assert sil[0].any() and sil[1].any() and not sil[3].any()  # the last looks away from the boxes

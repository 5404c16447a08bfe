"""The missing-part cue of the structure's hidden contours: a block (class structure) and a small part in front of
its outline. Present, the part hides that outline whatever its own contrast (drawn in the water's grey it is
invisible, yet the outline stays hidden); absent, the outline shows. And the per-frame verdict it gives."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from infer_testdata import look_at
from test_track import TRACK_SCENE

from cadalign.infer.track.config import TrackRunConfig
from cadalign.infer.track.edges import EdgeFit
from cadalign.infer.track.hidden import HiddenContours, HiddenSeen
from cadalign.infer.track.missing import PartMemory, part_records
from cadalign.infer.track.tracker import TrackStep
from cadalign.raycast.core import RaycastRenderer
from cadalign.sim.structure import load_structure
from cadalign.types import Camera

PARTS = ('[[objects]]\nname = "block"\nsource = "procedural:box"\nclass_name = "structure"\n'
         'position = [0.0, 0.0, 0.0]\n'
         'size_m = [2.0, 2.0, 2.0]\ntexture = "painted_steel"\n\n'
         '[[objects]]\nname = "valve"\nsource = "procedural:box"\nclass_name = "valve"\nposition = [1.0, -1.5, 0.5]\n'
         'size_m = [0.6, 0.6, 0.6]\ntexture = "painted_steel"\n')
CAM = Camera(np.array([[260.0, 0, 160], [0, 260.0, 120], [0, 0, 1]]), 320, 240)
WATER = 30.0


@pytest.fixture(scope="module")
def block(tmp_path_factory: pytest.TempPathFactory):
    path = tmp_path_factory.mktemp("hidden") / "block.toml"
    path.write_text(TRACK_SCENE.format(objects=PARTS))
    structure = load_structure(path)
    T_wc = look_at(np.array([0.5, -6.0, 2.0]), np.array([0.0, 0.0, 0.5]))
    light = np.array([0.3, -0.5, -0.8]) / np.linalg.norm([0.3, -0.5, -0.8])
    meshes = structure.render_meshes()

    def image(with_valve: bool, faint: bool = False) -> tuple[np.ndarray, np.ndarray]:
        f = RaycastRenderer([m for m in meshes if with_valve or m.instance != 2], CAM).render(T_wc,
                                                                                            with_full_masks=False)
        shade = 60 + 150 * np.abs(f.normals_cam @ (T_wc.R.T @ light))
        img = np.where(f.instance > 0, shade, WATER)
        if faint:
            img = np.where(f.instance == 2, WATER, img)  # the valve as dark as the water behind the block
        return img.astype(np.float32), f.instance

    return structure, T_wc, image


def test_hidden_contours_tell_an_absent_part_from_a_faint_one(block) -> None:
    structure, T_wc, image = block
    cue = HiddenContours(structure, CAM)
    _, instance = image(True)
    step = SimpleNamespace(T_cam_from_world=T_wc.inverse(), fit=SimpleNamespace(instance=instance))
    seen = {case: cue.seen(image(*args)[0], step)[2] for case, args in
            {"present": (True,), "faint": (True, True), "absent": (False,)}.items()}
    assert all(h.samples >= 20 and h.deep_samples >= 5 for h in seen.values())  # it hides a stretch of the outline
    assert seen["present"].seen < 0.1 and seen["faint"].seen < 0.1  # hidden by the part, however faint it is
    assert seen["absent"].seen > 0.6  # shown where the part is not
    assert seen["present"].deep_seen < 0.1 and seen["faint"].deep_seen < 0.1 and seen["absent"].deep_seen > 0.6
    assert cue.seen(image(True)[0], SimpleNamespace(T_cam_from_world=None, fit=None)) == {}  # a lost frame


def _valve_step(own_edges: float) -> TrackStep:
    """A tracked frame (frame support 0.8) whose valve (instance 2, a 40x40 px visible mask) has 40 contour samples,
    ``own_edges`` of them (and of its found edges) on image edges."""
    instance = np.zeros((CAM.height, CAM.width), np.int32)
    instance[100:140, 150:190] = 2  # the valve's visible mask
    fit = EdgeFit(look_at(np.array([0.5, -6.0, 2.0]), np.zeros(3)), 500, 0.8, 0.2, {2: (40, own_edges, own_edges)},
                  instance=instance)
    return TrackStep(0, "ok", fit.T_world_from_cam.inverse(), fit, "track", 0.0)


def test_hidden_contours_decide_a_part_whatever_its_own_edges(block) -> None:
    structure = block[0]
    step = _valve_step(own_edges=0.0)  # no image edges on the valve's own outline
    cfg = TrackRunConfig()

    def missing(hidden: dict | None) -> bool:
        return part_records(step, 0, "f", structure, cfg, PartMemory(), hidden)[1] == ["valve"]

    assert missing(None)  # no image edges on its outline: missing, by its own edges
    assert not missing({2: HiddenSeen(25, 0.1, 0, np.nan)})  # but it hides the structure's outline: it is there
    assert missing({2: HiddenSeen(25, 0.6, 0, np.nan)})  # the outline shows (or texture fools the search): its edges
    assert missing({2: HiddenSeen(5, 0.1, 0, np.nan)})  # too few hidden samples to say: its own edges decide


def test_deep_hidden_contours_pooled_over_frames_call_a_part_missing(block) -> None:
    """A part whose own outline finds edges (texture behind an absent valve can) is missing once the structure's
    contours deep inside its outline, pooled over frames, show as the rest of the structure does."""
    structure = block[0]
    step = _valve_step(own_edges=0.7)
    cfg = TrackRunConfig()

    def verdicts(deep_seen: float, frames: int = 5) -> list[bool]:
        memory = PartMemory()
        return [part_records(step, k, "f", structure, cfg, memory, {2: HiddenSeen(12, deep_seen, 8, deep_seen)})[1]
                == ["valve"] for k in range(frames)]

    # 8 deep samples a frame: 24 >= absent_samples from the third frame; seen 0.75 >= 0.85 x the frame's 0.8
    # support; a part found present is called missing after confirm_missing (2) such verdicts in a row
    assert verdicts(0.75) == [False, False, False, True, True]
    assert not any(verdicts(0.5))  # below the share: present, as its own edges say
    assert cfg.absent_samples > 16 and cfg.confirm_missing == 2  # what the first case's count of frames rests on


def test_track_jsonl_writes_a_part_without_deep_samples_as_strict_json(block) -> None:
    """A part that hides no deep sample has no deep share: track.jsonl writes null there, not NaN (which strict
    JSON readers refuse)."""
    import json

    from cadalign.infer.track.run import _step_json

    structure = block[0]
    step = _valve_step(own_edges=0.7)
    line = json.dumps(_step_json(step, "f", [], structure, {2: HiddenSeen(4, 0.25, 0, np.nan)}), allow_nan=False)
    assert json.loads(line)["part_hidden"] == {"valve": [4, 0.25, 0, None]}

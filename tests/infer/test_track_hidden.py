"""The missing-part cue of the structure's hidden contours: a block (class structure) and a small part in front of
its outline. Present, the part hides that outline whatever its own contrast (drawn in the water's grey it is
invisible, yet the outline stays hidden); absent, the outline shows. And the per-frame verdict it gives."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from infer_testdata import look_at
from test_track import TRACK_SCENE

from cadalign.infer.track.edges import EdgeFit
from cadalign.infer.track.hidden import HiddenContours
from cadalign.infer.track.run import PartMemory, TrackRunConfig, part_records
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
    assert all(n >= 20 for n, _ in seen.values())  # the valve hides a stretch of the block's outline
    assert seen["present"][1] < 0.1 and seen["faint"][1] < 0.1  # hidden by the part, however faint it is
    assert seen["absent"][1] > 0.6  # shown where the part is not
    assert cue.seen(image(True)[0], SimpleNamespace(T_cam_from_world=None, fit=None)) == {}  # a lost frame


def test_hidden_contours_decide_a_part_whatever_its_own_edges(block) -> None:
    structure = block[0]
    instance = np.zeros((CAM.height, CAM.width), np.int32)
    instance[100:140, 150:190] = 2  # the valve's visible mask
    fit = EdgeFit(look_at(np.array([0.5, -6.0, 2.0]), np.zeros(3)), 500, 0.8, 0.2, {2: (40, 0.0, 0.0)},
                  instance=instance)
    step = TrackStep(0, "ok", fit.T_world_from_cam.inverse(), fit, "track", 0.0)
    cfg = TrackRunConfig()

    def missing(hidden: dict | None) -> bool:
        return part_records(step, 0, "f", structure, cfg, PartMemory(), hidden)[1] == ["valve"]

    assert missing(None)  # no image edges on its outline: missing, by its own edges
    assert not missing({2: (25, 0.1)})  # but it hides the structure's outline: it is there
    assert missing({2: (25, 0.6)})  # the outline shows there (or texture fools the search): its own edges decide
    assert missing({2: (5, 0.1)})  # too few hidden samples to say: its own edges decide

"""Repairing a broken SfM model by re-mapping a window round each break (cadalign.sfm.repair)."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.config import from_dict
from cadalign.errors import DegenerateGeometryError
from cadalign.evaluate.sfm import GT_SCENE, pose_errors
from cadalign.io import read_json
from cadalign.sfm import mapping
from cadalign.sfm.config import SfMConfig
from cadalign.sfm.consistency import Break, Consistency
from cadalign.sfm.pipeline import Layout, _kept_names
from cadalign.sfm.refine import refine
from cadalign.sfm.repair import break_windows, repair_breaks
from cadalign.sfm.report import cameras_json

runner = CliRunner()


@settings(max_examples=60, deadline=None)
@given(st.integers(8, 80), st.integers(6, 20), st.data())
def test_windows_hold_every_seam_are_disjoint_and_clipped(n: int, frames: int, data: st.DataObject):
    names = [f"{k:06d}" for k in range(n)]
    seams = sorted(data.draw(st.lists(st.integers(1, n - 1), min_size=1, max_size=4, unique=True)))
    cons = Consistency(n - 1, 0.3, 9.0, tuple(Break(names[i - 1], names[i], 100, 9.0) for i in seams))
    spans = break_windows(names, cons, frames)
    assert all(0 <= lo < hi <= n for lo, hi in spans)
    assert all(a[1] <= b[0] for a, b in zip(spans, spans[1:], strict=False))  # disjoint, in order
    for i in seams:  # each seam (i-1, i) lies inside one window, with frames on both sides of it
        assert any(lo <= i - 1 and i < hi for lo, hi in spans)
    if len(seams) == 1 and frames // 2 <= seams[0] <= n - (frames - frames // 2):
        assert spans == [(seams[0] - frames // 2, seams[0] - frames // 2 + frames)]  # centred, full length


@pytest.fixture(scope="module")
def mapped(tiny_dive: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sfm_repair") / "out"
    res = runner.invoke(app, ["sfm", str(tiny_dive / "frames"), "--out", str(out), "--set", "num_threads=1"])
    assert res.exit_code == 0, res.output
    return out


def _setup(mapped: Path, tmp_path: Path,
           **mapper: object) -> tuple[SfMConfig, Layout, list[str], pycolmap.Reconstruction]:
    """A copy of the SfM folder (mapping writes database copies beside it), its config and its model."""
    root = tmp_path / "sfm"
    root.mkdir(parents=True)
    for name in ("database.db", "frames.json"):
        shutil.copy(mapped / name, root / name)
    (root / "images").symlink_to(mapped / "images")
    cfg = from_dict(SfMConfig, read_json(mapped / "cadalign_stage.json")["config"]["sfm"])
    cfg = dataclasses.replace(cfg, mapper=dataclasses.replace(cfg.mapper, **mapper))
    lay = Layout(root)
    return cfg, lay, _kept_names(lay), pycolmap.Reconstruction(str(mapped / "sparse" / "0"))


def _hinge(rec: pycolmap.Reconstruction, names: list[str], at: int, deg: float) -> pycolmap.Reconstruction:
    """A copy of ``rec`` with frames ``names[at:]`` turned about the first camera's centre: a hinge."""
    out = pycolmap.Reconstruction(rec)
    by_name = {im.name: im for im in out.images.values()}
    c = np.asarray(by_name[names[0]].projection_center())
    R = Rotation.from_euler("z", deg, degrees=True).as_matrix()
    turn = pycolmap.Rigid3d(pycolmap.Rotation3d(R), c - R @ c)  # x -> R (x - c) + c
    for n in names[at:]:
        im = by_name[n]
        out.frames[im.frame_id].rig_from_world = im.cam_from_world() * turn
    return out


def test_a_hinged_model_is_repaired_by_remapping_a_window_round_the_break(mapped: Path, tiny_dive: Path,
                                                                          tmp_path: Path):
    cfg, lay, names, sound = _setup(mapped, tmp_path, repair_frames=6)
    assert len(names) == 10 and sound.num_reg_images() == 10
    broken = _hinge(sound, names, 5, 4.0)
    cons = mapping._consistency(cfg, lay, broken, names)
    assert [(b.frame_a, b.frame_b) for b in cons.breaks] == [(names[4], names[5])]
    repaired, report = mapping._repair(cfg, lay, broken, names, cons, tmp_path / "work", None)
    assert report["repaired"], report
    assert [w["frames"] for w in report["windows"]] == [[names[2], names[7]]]
    assert repaired.num_reg_images() == 10 and report["consistency"]["breaks"] == []
    refine(repaired, cfg)  # what the pipeline's next step does (the sound model had it)
    truth = read_json(tiny_dive / GT_SCENE / "cameras.json")
    err = {k: pose_errors(cameras_json(m), truth).rel_rot_err_deg for k, m in
           (("sound", sound), ("broken", broken), ("repaired", repaired))}
    assert err["broken"].max() > 3.5  # the hinge
    # every consecutive relative rotation is as right as in the sound model again, the seam included
    assert err["repaired"].max() < max(0.2, 1.5 * err["sound"].max())


def test_every_attempt_broken_is_repaired_or_cut_to_the_largest_piece(mapped: Path, tmp_path: Path,
                                                                      monkeypatch: pytest.MonkeyPatch):
    """The mapping step's fallbacks, with a mapper that always returns the same hinged model."""
    for mode, kept in (("repair", 10), ("largest_piece", 6), ("keep_all", 10)):
        cfg, lay, names, sound = _setup(mapped, tmp_path / mode, repair_frames=6, attempts=2, on_break=mode)
        broken = _hinge(sound, names, 6, 4.0)
        real = mapping._map_once

        def map_once(c, la, sub, work, progress, b=broken, n=names, real=real):
            if sub != n:  # a repair window: mapped for real
                return real(c, la, sub, work, progress)
            return [pycolmap.Reconstruction(b)], {"mapper": "incremental"}

        monkeypatch.setattr(mapping, "_map_once", map_once)
        model, info = mapping._map_with_attempts(cfg, lay, names, tmp_path / mode / "work", None)
        assert [len(a["breaks"]) for a in info["attempts"]] == [1, 1]
        assert model.num_reg_images() == kept, mode
        assert ("repair" in info) == (mode == "repair")
        if mode == "repair":
            assert info["repair"]["repaired"] and info["consistency"]["breaks"] == []
        if mode == "largest_piece":
            assert sorted(info["unregistered"]) == names[6:]
            assert all("consistency break" in why for why in info["unregistered"].values())


def test_a_window_that_breaks_too_gives_no_repair_and_says_why(mapped: Path):
    rec = pycolmap.Reconstruction(str(mapped / "sparse" / "0"))
    names = sorted(im.name for im in rec.images.values())
    cons = Consistency(9, 0.3, 9.0, (Break(names[4], names[5], 100, 9.0),))
    merged = []
    out, report = repair_breaks(rec, names, cons, 6, lambda sub, k: (rec, cons),
                                lambda models, adds: merged.append(models), lambda m: cons)
    assert out is None and not report["repaired"] and not merged
    assert report["why_not"] == f"the window {names[2]}..{names[7]} mapped on its own breaks too"


def test_a_window_with_no_model_gives_no_repair_instead_of_failing_the_run(mapped: Path):
    # seen on opensfm_lund (street, forward motion) with the fast preset: a 16-frame window had no initial pair
    rec = pycolmap.Reconstruction(str(mapped / "sparse" / "0"))
    names = sorted(im.name for im in rec.images.values())
    cons = Consistency(9, 0.3, 9.0, (Break(names[4], names[5], 100, 9.0),))

    def no_model(sub: list[str], k: int):
        raise DegenerateGeometryError("SfM found no model")

    out, report = repair_breaks(rec, names, cons, 6, no_model, lambda models, adds: None, lambda m: cons)
    assert out is None and not report["repaired"]
    assert report["why_not"].startswith(f"the window {names[2]}..{names[7]} found no model on its own")
    assert report["windows"] == [{"frames": [names[2], names[7]], "registered": 0, "breaks": 0}]


def test_a_broken_first_pass_is_repaired_before_it_proposes_loop_pairs(mapped: Path, tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch):
    cfg, lay, names, sound = _setup(mapped, tmp_path, repair_frames=6)
    broken = _hinge(sound, names, 5, 4.0)
    real = mapping.colmap.reconstruct
    seen = []

    def reconstruct(c, db, images, work, sub, progress):
        seen.append(len(sub))
        if sub == names:  # the first pass over all frames comes out hinged
            return mapping.colmap.MappingResult([pycolmap.Reconstruction(broken)], "incremental")
        return real(c, db, images, work, sub, progress)

    monkeypatch.setattr(mapping.colmap, "reconstruct", reconstruct)
    proposed_from = []
    monkeypatch.setattr(mapping, "model_loop_pairs", lambda rec, n, c: proposed_from.append(rec) or [])
    models, info = mapping._map_once(cfg, lay, names, tmp_path / "work", None)
    assert seen == [10, 6]  # the first pass, then the window round the hinge
    assert info["first_pass_repair"]["repaired"]
    assert proposed_from == [models[0]]  # loop pairs come from the repaired model, which is kept
    assert mapping._consistency(cfg, lay, models[0], names).ok and models[0].num_reg_images() == 10

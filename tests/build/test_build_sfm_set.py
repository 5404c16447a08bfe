"""``build-dataset --sfm-set``: SfM settings over the preset's, checked strictly, refused for a jobs file."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cadalign import sfm
from cadalign.cli.main import app
from cadalign.testing.tiny_scene import write_tiny_scene

runner = CliRunner()


class _Stop(Exception):
    pass


def test_sfm_settings_reach_the_sfm_stage_and_bad_ones_are_named(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    spec = write_tiny_scene(tmp_path / "scene.toml", effects=[])
    frames = tmp_path / "frames"
    frames.mkdir()
    seen = []

    def run(cfg, source, out, **kw):  # stop where SfM would start: the resolved config is what matters
        seen.append(cfg)
        raise _Stop

    # build_dataset calls cadalign.sfm.run under the name it imported it as, in its own module
    monkeypatch.setattr(importlib.import_module("cadalign.build.run"), "sfm_run", run)
    args = ["build-dataset", str(frames), "--cad", str(spec), "--out", str(tmp_path / "out")]
    res = runner.invoke(app, [*args, "--sfm-set", "mapper.repair_frames=20", "--sfm-set", "matching.overlap=12"])
    assert isinstance(res.exception, _Stop), res.output
    base = sfm.PRESETS["balanced"]
    assert seen[0].mapper.repair_frames == 20 and seen[0].matching.overlap == 12
    assert seen[0].mapper.attempts == base.mapper.attempts and seen[0].features == base.features  # the rest: preset

    res = runner.invoke(app, [*args, "--sfm-set", "mapper.repair_frame=20"])
    assert res.exit_code != 0 and len(seen) == 1
    assert "repair_frame" in res.output and "--sfm-set" in res.output

    jobs = tmp_path / "jobs.toml"
    jobs.write_text(f'[[video]]\nname = "a"\nsource = "{frames}"\n')
    res = runner.invoke(app, ["build-dataset", str(jobs), "--cad", str(spec), "--out", str(tmp_path / "many"),
                              "--sfm-set", "matching.overlap=12"])
    assert res.exit_code != 0 and "--sfm-set is for one video" in res.output

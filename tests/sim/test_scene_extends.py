"""``extends``: a scene file that starts from another one (tables merge key by key, lists replace)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from cadalign.config import ConfigError
from cadalign.sim.spec import load_scene, resolve_source
from cadalign.testing.tiny_scene import write_tiny_scene

MESH = "v 0 0 0\nv 0.4 0 0\nv 0 0.4 0\nv 0 0 0.4\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def _base(tmp_path: Path) -> Path:
    """The tiny scene in ``tmp/base/`` with one more part whose mesh path is relative to that folder."""
    (tmp_path / "base" / "meshes").mkdir(parents=True)
    (tmp_path / "base" / "meshes" / "tet.obj").write_text(MESH)
    path = write_tiny_scene(tmp_path / "base" / "tiny.toml", effects=["attenuation"])
    path.write_text(path.read_text() + '\n[[objects]]\nname = "tet"\nsource = "meshes/tet.obj"\nunit = "m"\n'
                    'class_name = "structure"\nposition = [0.0, 1.2, 0.0]\n')
    return path


def test_a_scene_changes_one_trajectory_knob_of_another(tmp_path: Path) -> None:
    base_path = _base(tmp_path)
    (tmp_path / "runs").mkdir()
    child = tmp_path / "runs" / "lower.toml"
    child.write_text('extends = "../base/tiny.toml"\nname = "lower"\n[trajectory]\nheight_m = 1.2\nframes = 6\n')
    base, got = load_scene(base_path), load_scene(child)
    assert got.trajectory == replace(base.trajectory, height_m=1.2, frames=6)  # the other keys are the base's
    assert got.name == "lower" and got.effects == base.effects and got.water == base.water
    assert [o.name for o in got.objects] == [o.name for o in base.objects]
    # the base's relative mesh path still names its file when read from the child's folder
    tet = next(o for o in got.objects if o.name == "tet")
    assert resolve_source(tet.source, child) == (tmp_path / "base" / "meshes" / "tet.obj").resolve()
    with pytest.raises(Exception, match="mesh not found"):
        resolve_source(next(o for o in base.objects if o.name == "tet").source, child)


def test_lists_replace_the_base_list(tmp_path: Path) -> None:
    _base(tmp_path)
    child = tmp_path / "base" / "one.toml"
    child.write_text('extends = "tiny.toml"\neffects = ["attenuation", "backscatter"]\n[[objects]]\nname = "only"\n'
                     'source = "procedural:box"\nclass_name = "structure"\nsize_m = [1.0, 1.0, 1.0]\n')
    got = load_scene(child)
    assert [o.name for o in got.objects] == ["only"] and got.effects == ("attenuation", "backscatter")


def test_two_levels_of_extends(tmp_path: Path) -> None:
    _base(tmp_path)
    (tmp_path / "base" / "a.toml").write_text('extends = "tiny.toml"\n[trajectory]\nframes = 5\n')
    (tmp_path / "base" / "b.toml").write_text('extends = "a.toml"\n[trajectory]\nradius_m = 3.5\n')
    t = load_scene(tmp_path / "base" / "b.toml").trajectory
    assert (t.frames, t.radius_m, t.height_m) == (5, 3.5, 1.6)


@pytest.mark.parametrize(("text", "match"), [
    ('extends = "b.toml"\n', "makes a loop"),
    ('extends = "a.toml"\n', "cannot extend itself"),
    ('extends = "nowhere.toml"\n', "nowhere.toml.*is not a file; the path is relative to"),
    ("extends = 3\n", "extends must name a scene file"),
])
def test_bad_extends_are_refused_naming_the_file(tmp_path: Path, text: str, match: str) -> None:
    (tmp_path / "a.toml").write_text(text)
    (tmp_path / "b.toml").write_text('extends = "a.toml"\n')
    with pytest.raises(ConfigError, match=match) as exc:
        load_scene(tmp_path / "a.toml")
    assert "a.toml" in str(exc.value)


def test_an_unknown_key_in_the_extending_file_is_still_refused(tmp_path: Path) -> None:
    _base(tmp_path)
    child = tmp_path / "base" / "typo.toml"
    child.write_text('extends = "tiny.toml"\n[trajectory]\nhieght_m = 2.0\n')
    with pytest.raises(ConfigError, match="hieght_m"):
        load_scene(child)

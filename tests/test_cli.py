from __future__ import annotations

import subprocess
import sys

import pytest
from typer.testing import CliRunner

from cadalign import __version__
from cadalign.cli.main import app

SUBCOMMANDS = ["sim", "sfm", "align", "build-dataset", "train", "eval", "infer", "fuse", "emulate", "bench", "demo",
               "bag"]
runner = CliRunner()


def test_help_lists_every_subcommand():
    res = runner.invoke(app, ["--help"])
    assert res.exit_code == 0
    for cmd in SUBCOMMANDS:
        assert cmd in res.output


@pytest.mark.parametrize("cmd", SUBCOMMANDS)
def test_each_subcommand_has_help(cmd):
    res = runner.invoke(app, [cmd, "--help"])
    assert res.exit_code == 0, res.output
    assert "Usage" in res.output


def test_version():
    res = runner.invoke(app, ["--version"])
    assert res.exit_code == 0 and __version__ in res.output


def test_bad_log_level_is_rejected():
    res = runner.invoke(app, ["--log-level", "loud", "sim", "--help"])
    assert res.exit_code != 0


def test_sim_with_misspelled_scene_key_fails_readably(tmp_path):
    scene = tmp_path / "s.toml"
    scene.write_text('name = "x"\neffekts = []\n[[objects]]\nname = "a"\nsource = "procedural:box"\n')
    res = runner.invoke(app, ["sim", str(scene), "--out", str(tmp_path / "o")])
    assert res.exit_code == 1
    assert "effekts" in res.output and "did you mean 'effects'" in res.output


def test_import_geometry_is_light():
    code = (
        "import sys, cadalign.geometry; "
        "bad=[m for m in ('torch','open3d','pyrender','pycolmap') if m in sys.modules]; "
        "print(bad); sys.exit(1 if bad else 0)"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr


def test_a_progress_bar_runs_no_thread_and_an_abandoned_one_closes_from_any_thread():
    """cli.common.track redraws from the iterating thread: rich's own ``track`` starts two threads, and an abandoned
    one closed by the garbage collector inside its refresh thread hung a test run (s60)."""
    import threading

    from cadalign.cli.common import track

    before = threading.active_count()
    seen = []
    for i in track(range(5), "items"):
        seen.append(i)
        assert threading.active_count() == before
    assert seen == [0, 1, 2, 3, 4]
    left = track(iter(range(100)), "left early")  # no len: the bar's total stays open
    assert next(left) == 0 and threading.active_count() == before
    closer = threading.Thread(target=left.close)
    closer.start()
    closer.join(timeout=10)
    assert not closer.is_alive()
    with pytest.raises(StopIteration):
        next(left)

"""Bad inputs through the CLI: a one-line ``error:`` naming the input, exit code 1, no traceback."""

from __future__ import annotations

from pathlib import Path

from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.testing.tiny_scene import write_tiny_scene

runner = CliRunner()


def _fails_readably(args: list[str], *fragments: str) -> str:
    res = runner.invoke(app, args)
    out = " ".join(res.output.split())  # rich wraps long lines
    assert res.exit_code == 1, res.output
    assert "error:" in out and "Traceback" not in out
    squeezed = "".join(out.split())  # rich may also wrap inside a long word (a path)
    for frag in fragments:
        assert "".join(frag.split()) in squeezed, (frag, out)
    return out


def test_sfm_zero_length_video(tmp_path: Path) -> None:
    (tmp_path / "dive.mp4").write_bytes(b"")
    _fails_readably(["sfm", str(tmp_path / "dive.mp4"), "--out", str(tmp_path / "o"), "--preset", "fast"],
                    "dive.mp4", "is empty (0 bytes)")


def test_sfm_config_with_misspelled_key(tmp_path: Path) -> None:
    (tmp_path / "sfm.toml").write_text("[matching]\noverlapp = 5\n")
    _fails_readably(["sfm", str(tmp_path), "--out", str(tmp_path / "o"), "--config", str(tmp_path / "sfm.toml")],
                    "sfm.toml", "unknown key 'matching.overlapp'", "did you mean 'matching.overlap'")


def test_sim_camera_inside_an_object(tmp_path: Path) -> None:
    scene = write_tiny_scene(tmp_path / "s.toml", effects=[], frames=2)
    scene.write_text(scene.read_text().replace("radius_m = 3.2\nheight_m = 1.6", "radius_m = 0.2\nheight_m = 0.5"))
    _fails_readably(["sim", str(scene), "--out", str(tmp_path / "o")], "inside object 'block'")


def test_ctrl_c_is_a_one_line_note_and_exit_130() -> None:
    """KeyboardInterrupt inside a command (Ctrl-C, or a stage that stops itself with a reason) -> exit 130 and
    one line: the reason if the stage gave one, else how to resume; never a traceback."""
    import typer

    from cadalign.cli.common import user_errors

    mini = typer.Typer()

    @mini.command()
    def work(reason: str = "") -> None:
        with user_errors():
            raise KeyboardInterrupt(reason) if reason else KeyboardInterrupt

    res = runner.invoke(mini, [])
    assert res.exit_code == 130 and res.output.strip() == (
        "interrupted: finished work is kept on disk; re-run the same command to resume")
    res = runner.invoke(mini, ["--reason", "training interrupted at step 3; re-run the demo to resume"])
    assert res.exit_code == 130 and res.output.strip() == (
        "interrupted: training interrupted at step 3; re-run the demo to resume")

"""Ctrl-C for real: long ``cadalign`` commands run as child processes get SIGINT (``os.kill``) part-way,
exit promptly with code 130 and a one-line note, leave no torn file, and re-running the same command
finishes with a result byte-identical to an uninterrupted run (without redoing the finished steps)."""

from __future__ import annotations

import shutil
import signal
from pathlib import Path

import pytest
from signal_testdata import (
    INTERRUPT_NOTE,
    assert_no_torn_files,
    cadalign,
    interrupt_when,
    record_interrupt,
    run_to_end,
    tree_digest,
)

from cadalign.errors import InputError
from cadalign.io import read_json
from cadalign.testing.tiny_scene import write_picks_from_truth, write_tiny_scene

BUILD_SCENE_EDITS = (  # the capture of tests/build: a closer orbit round a bigger block (SfM points on it)
    ("width = 160", "width = 320"), ("height = 120", "height = 240"), ("speed_mps = 0.5", "speed_mps = 0.3"),
    ("radius_m = 3.2", "radius_m = 3.0"), ("size_m = [1.2, 0.8, 0.6]", "size_m = [2.0, 1.4, 1.2]"),
    ("position = [0.0, 0.0, 0.3]", "position = [0.0, 0.0, 0.0]"), ("center = [0.0, 0.0, 0.5]",
    "center = [0.0, 0.0, 0.8]"), ("position = [-1.0, 0.9, 0.0]", "position = [-0.6, 0.0, 1.2]"),
    ("position = [0.9, -0.8, 0.1]", "position = [0.6, -0.3, 1.2]"),
)
BUILD_FRAMES = 12


@pytest.fixture(scope="module")
def build_case(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """A 12-frame 320x240 capture, its SfM (run once: pycolmap is not bitwise deterministic across runs, so
    both builds share it) and picks for the coarse alignment, in one folder: ``tiny.toml``, ``sim/``,
    ``picks.json``, ``sfm/``."""
    from cadalign.sfm import PRESETS, run
    from cadalign.sim.run import simulate

    root = tmp_path_factory.mktemp("sigbuild")
    spec = write_tiny_scene(root / "tiny.toml", effects=["attenuation", "backscatter"], frames=BUILD_FRAMES)
    text = spec.read_text()
    for a, b in BUILD_SCENE_EDITS:
        text = text.replace(a, b)
    spec.write_text(text)
    sim = simulate(spec, root / "sim", video=False, contact_sheet=False)
    sfm_dir = run(PRESETS["fast"], sim / "frames", root / "sfm")
    write_picks_from_truth(sfm_dir, sim, root / "picks.json", noise_m=0.0)
    return root


def _build_cmd(out: str) -> list[str]:
    return cadalign("build-dataset", "sim/frames", "--cad", "tiny.toml", "--out", out, "--preset", "fast",
                    "--init", "picks.json")


def test_build_dataset_sigint_mid_render_then_rerun_equals_an_uninterrupted_build(build_case: Path) -> None:
    """SIGINT once the first frame is rendered: exit 130 within seconds, finished frames whole, no temp files;
    the re-run reuses SfM (points3D.bin untouched), the alignment and the rendered frames (their records
    untouched), and the dataset is byte-identical to a build that was never interrupted.

    The uninterrupted reference build starts from the interrupted build's finished SfM and alignment: neither
    stage is bitwise reproducible from scratch (pycolmap and Open3D reduce in parallel threads; two alignments
    of one SfM model differ in the last bits), and reusing them is exactly what a resumed build does."""
    shutil.copytree(build_case / "sfm", build_case / "cut" / "sfm")
    scene = build_case / "cut" / "dataset" / "all" / "000000"
    stopped = interrupt_when(_build_cmd("cut"), build_case, lambda: (scene / "frames_json" / "000000.json").is_file())
    assert stopped.returncode == 130, stopped.stderr[-2000:]
    assert stopped.seconds_to_exit < 30, stopped.seconds_to_exit  # ~1 s on an idle machine
    assert "interrupted:" in stopped.stderr and INTERRUPT_NOTE in stopped.stderr
    assert "Traceback" not in stopped.stderr
    record_interrupt("build-dataset", "Ctrl-C (SIGINT) while rendering frames", stopped)
    done = sorted((scene / "frames_json").glob("*.json"))
    assert 1 <= len(done) < BUILD_FRAMES, f"the signal did not land mid-render: {len(done)} frames done"
    assert not (build_case / "cut" / "build_report.json").exists()
    assert_no_torn_files(build_case / "cut")
    for rec in done:  # a frame with a record has every file, whole
        name = f"{rec.stem}.png"
        assert all((scene / d / name).is_file() for d in ("rgb", "depth", "class", "instance", "depth_sfm"))

    for stage in ("sfm", "align"):
        shutil.copytree(build_case / "cut" / stage, build_case / "ref" / stage)
    run_to_end(_build_cmd("ref"), build_case)
    assert read_json(build_case / "ref" / "build_report.json")["frames"] == BUILD_FRAMES

    points = build_case / "cut" / "sfm" / "sparse" / "0" / "points3D.bin"
    align_stamp = (build_case / "cut" / "align" / "align.json").stat().st_mtime_ns
    sfm_stamp = points.stat().st_mtime_ns
    rec_stamps = {p.name: p.stat().st_mtime_ns for p in done}
    run_to_end(_build_cmd("cut"), build_case)
    assert points.stat().st_mtime_ns == sfm_stamp
    assert (build_case / "cut" / "align" / "align.json").stat().st_mtime_ns == align_stamp
    assert {p.name: p.stat().st_mtime_ns for p in done} == rec_stamps
    ref, cut = tree_digest(build_case / "ref" / "dataset"), tree_digest(build_case / "cut" / "dataset")
    assert len(ref) > 100 and sorted(ref) == sorted(cut)
    assert [k for k in ref if ref[k] != cut[k]] == [], f"interrupted after {len(done)} frames"
    assert read_json(build_case / "cut" / "build_report.json")["frames"] == BUILD_FRAMES


SEG_TOML = """
scale = 0.5
dice_weight = 0.5
[model]
base_channels = 4
depth = 3
[loop]
steps = 16
batch_size = 2
lr = 0.01
checkpoint_every = 2
log_every = 1
[augment]
enabled = true
"""


def test_train_seg_sigint_then_resume_equals_an_uninterrupted_run(tiny_bop: Path, tmp_path: Path) -> None:
    """SIGINT once the step-4 checkpoint exists: the loop finishes its step, writes last.pt and exits 130;
    ``--resume`` continues and the per-step losses (and the final weights) equal an uninterrupted run's."""
    import torch

    (tmp_path / "seg.toml").write_text(SEG_TOML)

    def cmd(out: str, *extra: str) -> list[str]:
        return cadalign("train", "seg", tiny_bop, "--config", "seg.toml", "--split", "all", "--out", out, *extra)

    run_to_end(cmd("full"), tmp_path)
    stopped = interrupt_when(cmd("cut"), tmp_path, lambda: (tmp_path / "cut/checkpoints/step_000004.pt").is_file())
    assert stopped.returncode == 130, stopped.stderr[-2000:]
    assert stopped.seconds_to_exit < 30
    assert "interrupted (continue with --resume)" in stopped.stderr and "Traceback" not in stopped.stderr
    record_interrupt("train seg", "Ctrl-C (SIGINT) mid-training", stopped)
    cut_rows = read_json(tmp_path / "cut" / "metrics.json")["rows"]
    assert 4 <= cut_rows[-1]["step"] < 16, f"the signal did not land mid-training: {cut_rows[-1]['step']}"
    assert_no_torn_files(tmp_path / "cut")
    run_to_end(cmd("cut", "--resume"), tmp_path)
    full = [(r["step"], r["loss"]) for r in read_json(tmp_path / "full" / "metrics.json")["rows"]]
    res = [(r["step"], r["loss"]) for r in read_json(tmp_path / "cut" / "metrics.json")["rows"]]
    assert [s for s, _ in full] == list(range(1, 17))
    assert res == full  # exactly: the sample stream, augmentation and optimiser state are restored
    a = torch.load(tmp_path / "full/checkpoints/last.pt", map_location="cpu", weights_only=False)["model"]
    b = torch.load(tmp_path / "cut/checkpoints/last.pt", map_location="cpu", weights_only=False)["model"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.slow
def test_sim_sigint_then_rerun_equals_an_uninterrupted_run(tmp_path: Path, shared_data: Path) -> None:
    """``cadalign sim``: SIGINT once three frames are written, exit 130; the re-run renders only the rest and
    every file (frames, BOP ground truth, contact sheet) is byte-identical to an uninterrupted run's; only
    sim_report.json's timings differ. (Slow: three simulator start-ups, ~30 s on a loaded 2-core machine.)"""
    write_tiny_scene(tmp_path / "tiny.toml", effects=["attenuation", "backscatter", "marine_snow"], frames=8)
    run_to_end(cadalign("sim", "tiny.toml", "--out", "ref", "--no-video"), tmp_path)
    stopped = interrupt_when(cadalign("sim", "tiny.toml", "--out", "cut", "--no-video"), tmp_path,
                             lambda: (tmp_path / "cut" / "frames" / "000002.png").is_file())
    assert stopped.returncode == 130 and INTERRUPT_NOTE in stopped.stderr, stopped.stderr[-2000:]
    assert stopped.seconds_to_exit < 20
    record_interrupt("sim", "Ctrl-C (SIGINT) while rendering frames", stopped)
    assert 3 <= len(list((tmp_path / "cut" / "frames").glob("*.png"))) < 8
    assert not (tmp_path / "cut" / "sim_report.json").exists()
    assert_no_torn_files(tmp_path / "cut")
    run_to_end(cadalign("sim", "tiny.toml", "--out", "cut", "--no-video"), tmp_path)
    ref, cut = (tree_digest(tmp_path / d, skip=lambda p: p.name == "sim_report.json") for d in ("ref", "cut"))
    assert len(ref) > 50 and ref == cut
    report = read_json(tmp_path / "cut" / "sim_report.json")
    assert 0 < report["frames_rendered_this_run"] <= 5


def _bench_points(path: Path) -> dict[str, dict]:
    try:
        return read_json(path)["stages"]["emulate"]["points"]
    except (InputError, KeyError):  # not written yet, or no setting finished yet
        return {}


@pytest.mark.slow
def test_bench_sigint_then_rerun_keeps_finished_settings_and_equals_an_uninterrupted_run(tmp_path: Path,
                                                                                         shared_data: Path) -> None:
    """``cadalign bench emulate --size tiny``: SIGINT once one setting is saved, exit 130 with bench.json whole;
    the re-run measures only the missing settings (the finished ones keep their records) and every setting's
    accuracy and deterministic metrics equal an uninterrupted run's (timings are measurements and differ)."""
    def cmd(out: str) -> list[str]:
        return cadalign("bench", "emulate", "--size", "tiny", "--out", out)

    run_to_end(cmd("ref"), tmp_path)
    stopped = interrupt_when(cmd("cut"), tmp_path, lambda: len(_bench_points(tmp_path / "cut" / "bench.json")) >= 1)
    assert stopped.returncode == 130 and INTERRUPT_NOTE in stopped.stderr, stopped.stderr[-2000:]
    record_interrupt("bench", "Ctrl-C (SIGINT) between benchmark settings", stopped)
    kept = _bench_points(tmp_path / "cut" / "bench.json")
    assert_no_torn_files(tmp_path / "cut")
    ref = _bench_points(tmp_path / "ref" / "bench.json")
    assert 1 <= len(kept) < len(ref) == 5, "the signal did not land mid-sweep"
    run_to_end(cmd("cut"), tmp_path)
    cut = _bench_points(tmp_path / "cut" / "bench.json")
    assert {k: cut[k] for k in kept} == kept  # finished settings were not measured again
    assert cut.keys() == ref.keys()
    for k in ref:
        assert cut[k]["status"] == ref[k]["status"] == "done"
        assert cut[k]["accuracy"] == ref[k]["accuracy"]
        assert {m: cut[k]["metrics"][m] for m in ("gap_m", "returns", "rays")} == \
            {m: ref[k]["metrics"][m] for m in ("gap_m", "returns", "rays")}


@pytest.mark.slow
def test_sfm_sigint_in_feature_extraction_then_rerun_completes(build_case: Path) -> None:
    """``cadalign sfm``: SIGINT while COLMAP extracts features (its C++ threads are stopped), exit 130 within
    seconds with no torn file; the re-run finishes the model. (SfM is not bitwise reproducible, so the result is
    checked for completeness, not against another run's bytes.)"""
    cmd = cadalign("sfm", "sim/frames", "--out", "sfm_cut", "--preset", "fast")
    stopped = interrupt_when(cmd, build_case, lambda: (build_case / "sfm_cut" / "database.db").is_file())
    assert stopped.returncode == 130 and INTERRUPT_NOTE in stopped.stderr, stopped.stderr[-2000:]
    assert stopped.seconds_to_exit < 30
    record_interrupt("sfm", "Ctrl-C (SIGINT) during feature extraction", stopped)
    assert not (build_case / "sfm_cut" / "sfm_report.json").exists()
    assert_no_torn_files(build_case / "sfm_cut")
    run_to_end(cmd, build_case)
    report = read_json(build_case / "sfm_cut" / "sfm_report.json")
    assert len(read_json(build_case / "sfm_cut" / "cameras.json")["frames"]) == BUILD_FRAMES, report


@pytest.mark.slow
def test_build_dataset_killed_mid_render_then_rerun_equals_an_uninterrupted_build(build_case: Path) -> None:
    """SIGKILL (no clean-up at all: a power cut, the OOM killer) once a frame is rendered: a frame's files may
    be torn, but its record is written last, so the re-run redoes exactly the unrecorded frames and the
    dataset is byte-identical to an uninterrupted build from the same SfM and alignment."""
    shutil.copytree(build_case / "sfm", build_case / "kill" / "sfm")
    scene = build_case / "kill" / "dataset" / "all" / "000000"
    killed = interrupt_when(_build_cmd("kill"), build_case, lambda: (scene / "frames_json" / "000000.json").is_file(),
                            sig=signal.SIGKILL)
    assert killed.returncode == -signal.SIGKILL
    done = sorted((scene / "frames_json").glob("*.json"))
    assert 1 <= len(done) < BUILD_FRAMES, f"the kill did not land mid-render: {len(done)} frames done"
    for stage in ("sfm", "align"):
        shutil.copytree(build_case / "kill" / stage, build_case / "ref_kill" / stage)
    run_to_end(_build_cmd("ref_kill"), build_case)
    run_to_end(_build_cmd("kill"), build_case)
    # a kill inside an atomic write leaves its hidden temp file (``.NAME.XXXX.tmp.EXT``): never read, harmless
    def stale(p: Path) -> bool:
        return p.name.startswith(".") and ".tmp" in p.name

    ref = tree_digest(build_case / "ref_kill" / "dataset")
    cut = tree_digest(build_case / "kill" / "dataset", skip=stale)
    assert sorted(ref) == sorted(cut)
    assert [k for k in ref if ref[k] != cut[k]] == [], f"killed after {len(done)} frames"


@pytest.mark.slow
def test_infer_sigint_leaves_no_partial_output_and_rerun_equals_an_uninterrupted_run(tmp_path: Path,
                                                                                      shared_data: Path) -> None:
    """``cadalign infer`` (oracle detector, ICP on simulated depth): its outputs are written through temp files and
    the temporal fusion is sequential, so SIGINT once it has opened them (the temp poses file exists) leaves no
    poses.jsonl/overlay.mp4 and no temp file, and
    the re-run (from the start) writes the same poses.jsonl as an uninterrupted run."""
    from cadalign.sim.run import simulate

    write_tiny_scene(tmp_path / "tiny.toml", effects=[], frames=8)
    simulate(tmp_path / "tiny.toml", tmp_path / "sim", video=False, contact_sheet=False)

    def cmd(out: str) -> list[str]:
        return cadalign("infer", "sim/frames", "--oracle-gt", "sim", "--cad", "tiny.toml", "--depth", "sim",
                        "--preset", "fast", "--out", out)

    run_to_end(cmd("ref"), tmp_path)
    stopped = interrupt_when(cmd("cut"), tmp_path, lambda: any((tmp_path / "cut").glob(".poses.jsonl.*")))
    assert stopped.returncode == 130 and INTERRUPT_NOTE in stopped.stderr, stopped.stderr[-2000:]
    assert stopped.seconds_to_exit < 30, stopped.seconds_to_exit
    record_interrupt("infer", "Ctrl-C (SIGINT) while processing the video", stopped)
    left = sorted(p.name for p in (tmp_path / "cut").iterdir())
    assert "poses.jsonl" not in left and "overlay.mp4" not in left and "timings.json" not in left, left
    assert not [n for n in left if ".tmp" in n], left
    run_to_end(cmd("cut"), tmp_path)
    assert (tmp_path / "cut" / "poses.jsonl").read_bytes() == (tmp_path / "ref" / "poses.jsonl").read_bytes()
    assert len((tmp_path / "ref" / "poses.jsonl").read_text().splitlines()) >= 8


@pytest.mark.slow
def test_train_seg_killed_then_resume_equals_an_uninterrupted_run(tiny_bop: Path, tmp_path: Path) -> None:
    """SIGKILL (no handler runs) once the step-4 checkpoint exists: ``--resume`` continues from the last
    checkpoint written atomically (steps after it are redone) and the per-step losses equal an uninterrupted
    run's: the metrics rows travel inside the checkpoint, so no row is lost or duplicated."""
    (tmp_path / "seg.toml").write_text(SEG_TOML)

    def cmd(out: str, *extra: str) -> list[str]:
        return cadalign("train", "seg", tiny_bop, "--config", "seg.toml", "--split", "all", "--out", out, *extra)

    run_to_end(cmd("full"), tmp_path)
    killed = interrupt_when(cmd("cut"), tmp_path, lambda: (tmp_path / "cut/checkpoints/step_000004.pt").is_file(),
                            sig=signal.SIGKILL)
    assert killed.returncode == -signal.SIGKILL
    import torch

    step = torch.load(tmp_path / "cut/checkpoints/last.pt", map_location="cpu", weights_only=False)["step"]
    # step_000004.pt is written before last.pt, so a kill between the two leaves last.pt one checkpoint behind
    assert 2 <= step < 16, f"the kill did not land mid-training: last.pt is at step {step}"
    run_to_end(cmd("cut", "--resume"), tmp_path)
    full = [(r["step"], r["loss"]) for r in read_json(tmp_path / "full" / "metrics.json")["rows"]]
    res = [(r["step"], r["loss"]) for r in read_json(tmp_path / "cut" / "metrics.json")["rows"]]
    assert res == full and len(full) == 16

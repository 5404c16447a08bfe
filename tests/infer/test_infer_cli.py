"""``cadalign infer`` and ``cadalign eval pose`` end to end on the tiny simulation with the oracle detector."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from cadalign.cli.main import app
from cadalign.io import read_json, write_image

runner = CliRunner()


def _infer(sim: Path, out: Path, *extra: str, source: Path | None = None):
    args = ["infer", str(source or sim / "frames"), "--oracle-gt", str(sim), "--cad", str(sim.parent / "tiny.toml"),
            "--out", str(out), *extra]
    return runner.invoke(app, args)


@pytest.mark.parametrize("cmd", [["infer"], ["eval", "pose"]])
def test_help(cmd: list[str]) -> None:
    res = runner.invoke(app, [*cmd, "--help"])
    assert res.exit_code == 0 and "Usage" in res.output


@pytest.fixture(scope="module")
def oracle_run(tiny_sim: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("infer") / "out"
    res = _infer(tiny_sim, out, "--gt", str(tiny_sim), "--depth", str(tiny_sim))
    assert res.exit_code == 0, res.output
    assert "ORACLE" in res.output
    return out


def test_end_to_end_with_the_oracle(oracle_run: Path) -> None:
    lines = (oracle_run / "poses.jsonl").read_text().splitlines()
    recs = [json.loads(x) for x in lines]
    assert recs and {r["class"] for r in recs} <= {"valve", "hot_stab"}
    for r in recs:
        T = np.asarray(r["T_cam_from_obj"])
        assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
        assert r["obj_id"] in (2, 3) and r["score"] == 1.0 and len(r["box_xyxy"]) == 4
        assert set(r["refine_iters"]) == {"silhouette", "depth"}
    assert (oracle_run / "overlay.mp4").stat().st_size > 0
    t = read_json(oracle_run / "timings.json")
    assert t["frames"] == 4 and t["detector"]["kind"] == "oracle"
    assert {"detector", "identify", "refinement", "temporal"} <= set(t["stages"])
    assert set(t["stages_ms"]) == {"detector", "pose", "refinement"} and t["stages_ms"]["refinement"] > 0
    ev = read_json(oracle_run / "eval.json")
    assert ev["fused"]["detection"]["f1"] == 1.0  # the oracle reports every target
    det, ref = ev["detector"]["overall"], ev["refined"]["overall"]
    # exact depth + exact masks: refinement must beat the 3 cm / 3 deg oracle noise
    assert ref["t_err_m"]["mean"] < 0.5 * det["t_err_m"]["mean"]
    assert ref["r_err_deg"]["mean"] < det["r_err_deg"]["mean"]
    assert ref["ar_mssd"] >= det["ar_mssd"]
    assert "| valve |" in (oracle_run / "eval.md").read_text()


def test_rerun_reuses_and_another_config_is_refused(tiny_sim: Path, oracle_run: Path) -> None:
    before = (oracle_run / "poses.jsonl").stat().st_mtime_ns
    res = _infer(tiny_sim, oracle_run, "--gt", str(tiny_sim), "--depth", str(tiny_sim))
    assert res.exit_code == 0 and (oracle_run / "poses.jsonl").stat().st_mtime_ns == before
    res = _infer(tiny_sim, oracle_run, "--refine-iters", "2")
    assert res.exit_code == 1 and "--overwrite" in res.output


def test_eval_pose_on_an_infer_folder(tiny_sim: Path, oracle_run: Path, tmp_path: Path) -> None:
    res = runner.invoke(app, ["eval", "pose", str(oracle_run), "--gt", str(tiny_sim), "--out", str(tmp_path)])
    assert res.exit_code == 0, res.output
    ev = read_json(tmp_path / "eval.json")
    assert ev["fused"]["detection"] == read_json(oracle_run / "eval.json")["fused"]["detection"]
    # a size cut above every part leaves no target: nothing is a hit or a miss, the oracle's poses are don't-care
    res = runner.invoke(app, ["eval", "pose", str(oracle_run), "--gt", str(tiny_sim), "--out", str(tmp_path / "cut"),
                              "--min-box-side-px", "10000"])
    assert res.exit_code == 0, res.output
    cut = read_json(tmp_path / "cut" / "eval.json")["fused"]
    assert cut["config"]["min_box_side_px"] == 10000 and cut["detection"]["tp"] == cut["detection"]["fn"] == 0
    assert ev["fused"]["detection"]["tp"] > 0


def test_video_without_parts_gives_empty_poses(tiny_sim: Path, tmp_path: Path) -> None:
    frames = tmp_path / "water"
    for i in range(3):
        write_image(frames / f"blank_{i}.png", np.full((120, 160, 3), 30, np.uint8))
    res = _infer(tiny_sim, tmp_path / "out", source=frames)
    assert res.exit_code == 0, res.output
    assert (tmp_path / "out" / "poses.jsonl").read_text() == ""
    assert read_json(tmp_path / "out" / "timings.json")["frames"] == 3


def test_an_overwrite_stopped_early_is_not_taken_for_the_older_complete_run(tiny_sim: Path, tmp_path: Path,
                                                                           monkeypatch) -> None:
    """A finished run, then the same folder with another config and --overwrite, stopped by Ctrl-C in its second
    frame: the older run's timings.json (the mark of a complete run) is gone, so the next run does not reuse it."""
    import cadalign.infer.run as infer_run

    frames = tmp_path / "water"
    for i in range(3):
        write_image(frames / f"blank_{i}.png", np.full((120, 160, 3), 30, np.uint8))
    assert _infer(tiny_sim, tmp_path / "out", source=frames).exit_code == 0
    real, seen = infer_run._infer_frame, []

    def stop(*args, **kwargs):
        seen.append(1)
        if len(seen) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(infer_run, "_infer_frame", stop)
    res = _infer(tiny_sim, tmp_path / "out", "--preset", "fast", "--overwrite", source=frames)
    assert res.exit_code == 130 and not (tmp_path / "out" / "timings.json").exists()


def test_a_detector_run_stopped_by_a_signal_resumes_to_the_uninterrupted_results(tiny_sim: Path, oracle_run: Path,
                                                                                   tmp_path: Path,
                                                                                   monkeypatch) -> None:
    """SIGINT/SIGTERM between frames 2 and 3 (as the run's signal flag sees it): exit 130 with the state saved, the
    finished frames' poses and overlay kept; the same command goes on from frame 3 and ends with the uninterrupted
    run's frames, poses (to the stored precision) and scores."""
    import contextlib

    import imageio.v2 as imageio

    import cadalign.infer.run as infer_run

    flag, real = {"stop": False}, infer_run._infer_frame
    calls = []

    def frame(*args, **kwargs):
        calls.append(1)
        out = real(*args, **kwargs)
        flag["stop"] = len(calls) == 2  # a signal arrives during frame 2: the run stops after it
        return out

    monkeypatch.setattr(infer_run, "stop_on_signals", contextlib.contextmanager(lambda: (yield flag)))
    monkeypatch.setattr(infer_run, "_infer_frame", frame)
    out = tmp_path / "out"
    res = _infer(tiny_sim, out, "--gt", str(tiny_sim), "--depth", str(tiny_sim))
    assert res.exit_code == 130 and "re-run the same command" in " ".join(res.output.split())
    assert (out / "infer_state.pkl").is_file() and not (out / "timings.json").exists()
    assert {json.loads(x)["frame"] for x in (out / "poses.jsonl.partial").read_text().splitlines()} == {0, 1}
    assert len(imageio.mimread(out / "overlay.part0.mp4")) == 2
    monkeypatch.undo()
    res = _infer(tiny_sim, out, "--gt", str(tiny_sim), "--depth", str(tiny_sim))
    assert res.exit_code == 0, res.output
    assert read_json(out / "frames.json") == read_json(oracle_run / "frames.json")
    assert not (out / "infer_state.pkl").exists() and not list(out.glob("*.partial")) and not list(out.glob("*.part*"))
    assert len(imageio.mimread(out / "overlay.mp4")) == 4
    ours, theirs = ([json.loads(x) for x in (d / "poses.jsonl").read_text().splitlines()] for d in (out, oracle_run))
    assert [(r["frame"], r["obj_id"], r["source"]) for r in ours] == [(r["frame"], r["obj_id"], r["source"])
                                                                      for r in theirs]
    for a, b in zip(ours, theirs, strict=True):
        assert np.allclose(a["T_cam_from_obj"], b["T_cam_from_obj"], atol=1e-9)
    scores = [read_json(d / "eval.json")["fused"]["detection"] for d in (out, oracle_run)]
    assert scores[0] == scores[1]


def test_corrupt_frame_is_skipped_and_named(tiny_sim: Path, tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    shutil.copytree(tiny_sim / "frames", frames)
    (frames / "000001.png").write_bytes(b"broken")
    res = _infer(tiny_sim, tmp_path / "out", "--preset", "fast", source=frames)
    assert res.exit_code == 0, res.output
    assert "000001.png" in res.output and "corrupt" in res.output
    assert read_json(tmp_path / "out" / "frames.json") == ["000000.png", "000002.png", "000003.png"]
    recs = [json.loads(x) for x in (tmp_path / "out" / "poses.jsonl").read_text().splitlines()]
    assert recs and "000001.png" not in {r["frame_name"] for r in recs}


def test_video_file_input(tiny_sim: Path, tmp_path: Path) -> None:
    res = _infer(tiny_sim, tmp_path / "out", "--preset", "fast", "--max-frames", "2", source=tiny_sim / "video.mp4")
    assert res.exit_code == 0, res.output
    assert read_json(tmp_path / "out" / "frames.json") == ["000000.png", "000001.png"]
    res = _infer(tiny_sim, tmp_path / "s", "--preset", "fast", "--stride", "2", source=tiny_sim / "video.mp4")
    assert res.exit_code == 0, res.output  # every second frame, under its own name
    assert read_json(tmp_path / "s" / "frames.json") == ["000000.png", "000002.png"]
    recs = [json.loads(x) for x in (tmp_path / "s" / "poses.jsonl").read_text().splitlines()]
    assert {r["frame_name"] for r in recs} <= {"000000.png", "000002.png"}


def test_ros_bag_input_with_topic_gives_the_folders_poses_and_stamps(tiny_sim: Path, oracle_run: Path,
                                                                     tmp_path: Path) -> None:
    """`infer BAG --topic T` (a ROS 1 bag of the frames, beside a second camera topic): the frames folder's
    poses, and each frame's header stamp in frame_stamps.json."""
    from bag_testdata import DT_NS, T0_NS, write_bag

    from cadalign.io import read_image

    frames = [read_image(p) for p in sorted((tiny_sim / "frames").glob("*.png"))]
    bag = write_bag(frames, tmp_path / "dive.bag", ros=1, other_topics=("/camera2/image_raw",))
    res = _infer(tiny_sim, tmp_path / "out", "--topic", "/camera/image_raw", "--gt", str(tiny_sim), "--depth",
                 str(tiny_sim), source=bag)  # as oracle_run was made from the folder
    assert res.exit_code == 0, res.output
    names = read_json(oracle_run / "frames.json")
    assert read_json(tmp_path / "out" / "frames.json") == names
    assert read_json(tmp_path / "out" / "frame_stamps.json") == {n: T0_NS + k * DT_NS for k, n in enumerate(names)}
    assert (tmp_path / "out" / "poses.jsonl").read_text() == (oracle_run / "poses.jsonl").read_text()
    from cadalign.infer.video import count_frames

    assert count_frames(bag, topic="/camera/image_raw", after=0) == len(frames) - 1  # a progress bar's total
    res = _infer(tiny_sim, tmp_path / "out2", source=bag)  # two image topics and none named
    assert res.exit_code == 1 and "--topic" in res.output and "/camera2/image_raw" in res.output


def test_detector_choice_errors(tiny_sim: Path, tmp_path: Path) -> None:
    res = runner.invoke(app, ["infer", str(tiny_sim / "frames"), "--cad", str(tiny_sim.parent / "tiny.toml"),
                              "--out", str(tmp_path / "o")])
    assert res.exit_code == 1 and "--model" in res.output and "--oracle-gt" in res.output
    res = runner.invoke(app, ["infer", str(tiny_sim / "frames"), "--cad", str(tiny_sim.parent / "tiny.toml"),
                              "--out", str(tmp_path / "o"), "--model", str(tmp_path / "no_run")])
    assert res.exit_code == 1 and "no trained model" in res.output


def test_predicted_depth_from_a_depth_network(tiny_sim: Path, tmp_path: Path) -> None:
    """``--depth RUN`` (a 'cadalign train depth' run): ICP runs on the network's metric depth of each frame, fed
    the raw frame prepared as its training images were, and the network's time is its own stage."""
    from cadalign.infer.dense import load_dense_model, metric_depth
    from cadalign.infer.detect import resolve_scene_dir
    from cadalign.infer.run import _DepthSource, is_depth_run
    from cadalign.io import read_image
    from cadalign.models.dispnet import DispNetConfig
    from cadalign.sfm import image_prep
    from cadalign.train.augment import AugmentConfig
    from cadalign.train.depth import DepthTrainConfig, train_depth
    from cadalign.train.loop import LoopConfig

    run = tmp_path / "depth_run"
    loop = LoopConfig(steps=2, batch_size=2, lr=1e-2, checkpoint_every=2, log_every=1, warmup=0.0)
    train_depth(DepthTrainConfig(model=DispNetConfig(base_channels=4, levels=3), loop=loop,
                                 augment=AugmentConfig(enabled=False), scale=0.5),
                resolve_scene_dir(tiny_sim), run, split="all")
    assert is_depth_run(run) and is_depth_run(run / "checkpoints" / "last.pt") and not is_depth_run(tiny_sim)
    rgb = read_image(tiny_sim / "frames" / "000000.png")
    src = _DepthSource(run)
    dm = load_dense_model(run, task="depth")
    prep = image_prep.to_feed(dict(image_prep.RAW), image_prep.read_run_prep(run), str(run))
    want = metric_depth(dm, image_prep.apply(rgb, prep))[0].numpy()
    K = np.array([[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]])
    got = src.get("000000.png", rgb, np.zeros_like(rgb), K)
    assert got.shape == rgb.shape[:2] and np.allclose(got, want) and (got > 0).all()
    prepared = rgb[:, ::-1].copy()  # frames said to be prepared already (enhance forced): fed as the detector's
    assert np.allclose(_DepthSource(run, raw_frames=False).get("x", rgb, prepared, K),
                       metric_depth(dm, prepared)[0].numpy())

    out = tmp_path / "out"
    res = _infer(tiny_sim, out, "--depth", str(run), "--preset", "fast")
    assert res.exit_code == 0, res.output
    recs = [json.loads(x) for x in (out / "poses.jsonl").read_text().splitlines()]
    assert recs and any(r["refine_iters"].get("depth", 0) > 0 for r in recs)
    t = read_json(out / "timings.json")
    assert t["stages"]["depth_net"]["mean_ms"] > 0 and t["stages_ms"]["depth_net"] > 0
    assert read_json(out / "cadalign_stage.json")["config"]["depth"] == str(run)

"""ROS 1 and ROS 2 bags as input: decoding every image encoding, the same frames and decisions as the frames
folder they were written from (plus the message stamps in frames.json), SfM and the CLI on a bag."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from bag_testdata import DT_NS, T0_NS, write_bag
from typer.testing import CliRunner

from cadalign.errors import InputError
from cadalign.formats.bag import image_topics, is_bag, iter_bag_frames
from cadalign.infer.video import iter_frames
from cadalign.io import read_image, read_json
from cadalign.sfm.config import FrameConfig
from cadalign.sfm.frames import extract_frames


def _frames(n: int = 3) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) for _ in range(n)]


@pytest.mark.parametrize(("ros", "kw"), [
    (1, {"encoding": "rgb8"}), (1, {"encoding": "bgr8"}), (1, {"compressed": True}), (1, {"encoding": "mono8"}),
    (2, {"encoding": "rgb8"}), (2, {"encoding": "mono16", "storage": "mcap"}), (2, {"compressed": True}),
])
def test_every_encoding_decodes_exactly_with_its_stamp(tmp_path: Path, ros: int, kw: dict) -> None:
    frames = _frames()
    bag = write_bag(frames, tmp_path / ("dive.bag" if ros == 1 else "dive"), ros=ros, **kw)
    assert is_bag(bag) and not is_bag(tmp_path)
    out = list(iter_bag_frames(bag))
    grey = kw.get("encoding", "").startswith("mono")
    for k, (f, ref) in enumerate(zip(out, frames, strict=True)):
        expected = np.repeat(ref[..., :1], 3, axis=2) if grey else ref  # a 12-bit mono16 shifts back exactly
        assert f.image.dtype == np.uint8 and np.array_equal(f.image, expected)
        assert (f.name, f.stamp_ns) == (f"{k:06d}.png", T0_NS + k * DT_NS)


def test_a_bag_gives_the_folders_frames_decisions_and_stamps(tiny_dive: Path, tmp_path: Path) -> None:
    """The simulator's frames written to a ROS 1 bag (raw rgb8) and a ROS 2 bag (png CompressedImage): the
    frame step selects and writes exactly the folder's frames, and the bag's frames carry their stamps."""
    folder = tiny_dive / "frames"
    frames = [read_image(p) for p in sorted(folder.glob("*.png"))]
    cfg = FrameConfig()
    ref = extract_frames(folder, cfg, tmp_path / "ref", tmp_path / "refm")
    for ros, kw in ((1, {}), (2, {"compressed": True})):
        bag = write_bag(frames, tmp_path / (f"dive{ros}.bag" if ros == 1 else f"dive{ros}"), ros=ros, **kw)
        got = extract_frames(bag, cfg, tmp_path / f"img{ros}", tmp_path / f"m{ros}")
        key = [(d.name, d.kept, d.reason, round(d.sharpness, 6), round(d.motion, 6)) for d in got]
        assert key == [(d.name, d.kept, d.reason, round(d.sharpness, 6), round(d.motion, 6)) for d in ref]
        assert [d.stamp_ns for d in got] == [T0_NS + k * DT_NS for k in range(len(frames))]
        assert all(d.stamp_ns is None for d in ref)
        for d in ref:
            if d.kept:
                written = read_image(tmp_path / f"img{ros}" / d.name)
                assert np.array_equal(written, read_image(tmp_path / "ref" / d.name))
        # infer reads the same frames under the same names
        assert [f.name for f in iter_frames(bag)] == [p.name for p in sorted(folder.glob("*.png"))]


@pytest.fixture(scope="module")
def bag_sfm(tiny_dive: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """(the ROS 2 bag of the tiny dive with a second camera topic, `cadalign sfm BAG --topic` output)."""
    from cadalign.cli.main import app

    root = tmp_path_factory.mktemp("bagsfm")
    frames = [read_image(p) for p in sorted((tiny_dive / "frames").glob("*.png"))]
    bag = write_bag(frames, root / "dive", ros=2, other_topics=("/camera2/image_raw",))
    res = CliRunner().invoke(app, ["sfm", str(bag), "--topic", "/camera/image_raw", "--out", str(root / "sfm"),
                                   "--preset", "fast"])
    assert res.exit_code == 0, res.output
    return bag, root / "sfm"


def test_sfm_on_a_bag_registers_and_records_stamps(bag_sfm: tuple[Path, Path], tiny_dive: Path) -> None:
    _, sfm = bag_sfm
    record = read_json(sfm / "frames.json")
    assert record["topic"] == "/camera/image_raw"
    kept = [f for f in record["frames"] if f["kept"]]
    assert all(f["stamp_ns"] == T0_NS + int(f["name"][:6]) * DT_NS for f in record["frames"])
    report = read_json(sfm / "sfm_report.json")
    assert report["registered"] >= len(kept) - 1 >= 5


def test_bag_topics_lists_and_a_missing_topic_names_them(bag_sfm: tuple[Path, Path], tmp_path: Path) -> None:
    from cadalign.cli.main import app

    bag, _ = bag_sfm
    res = CliRunner().invoke(app, ["bag", "topics", str(bag)])
    assert res.exit_code == 0 and "/camera/image_raw\tsensor_msgs/msg/Image\t10" in res.output
    assert [t.name for t in image_topics(bag)] == ["/camera/image_raw", "/camera2/image_raw"]
    with pytest.raises(InputError, match="2 image topics.*--topic"):
        list(iter_bag_frames(bag))
    res = CliRunner().invoke(app, ["sfm", str(bag), "--topic", "/nope", "--out", str(tmp_path / "o")])
    assert res.exit_code == 1 and "/nope is not an image topic" in res.output and "/camera2/image_raw" in res.output
    assert "Traceback" not in res.output
    shutil.copytree(bag, tmp_path / "copy")
    with pytest.raises(InputError, match="is for ROS bags"):
        list(iter_frames(tmp_path / "copy" / "metadata.yaml", topic="/x"))

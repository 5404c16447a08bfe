"""``InferConfig.enhance``: the detector sees the frames pre-processed as the dataset build did; the overlay
and everything else see the raw frames."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cadalign.config import ConfigError, from_dict
from cadalign.infer.config import PRESETS, InferConfig
from cadalign.infer.run import calibration_from_scene, run
from cadalign.infer.video import iter_frames
from cadalign.sfm.config import FrameConfig
from cadalign.sfm.frames import enhance


class _Recorder:
    """A detector that finds nothing and keeps what it was shown."""

    def __init__(self) -> None:
        self.images: list[np.ndarray] = []

    def detect(self, image: np.ndarray, K: np.ndarray) -> list:
        self.images.append(image.copy())
        return []


@pytest.mark.parametrize("how", ["none", "clahe", "clahe_wb"])
def test_the_detector_sees_the_frames_enhanced_as_asked(how: str, tiny_sim: Path, tiny_structure,
                                                        tmp_path: Path) -> None:
    scene = tiny_sim / "gt" / "sim" / "000000"
    cfg = dataclasses.replace(PRESETS["fast"], enhance=how, overlay=False)
    det = _Recorder()
    run(cfg, tiny_sim / "frames", det, tiny_structure.models, tiny_structure.class_names, tmp_path / "out",
        calib=calibration_from_scene(scene), detector_info={"kind": "test"})
    raw = [f.image for f in iter_frames(tiny_sim / "frames")]
    assert len(det.images) == len(raw) == 4
    for seen, frame in zip(det.images, raw, strict=True):
        want = frame if how == "none" else enhance(frame, FrameConfig(enhance=how))
        assert np.array_equal(seen, want)
        assert (how == "none") == np.array_equal(seen, frame)  # CLAHE changes these frames


def test_an_unknown_enhancement_is_refused() -> None:
    with pytest.raises(ConfigError, match="enhance"):
        from_dict(InferConfig, {"enhance": "gamma"})


def _recorded_run(tmp_path: Path, name: str, record: dict) -> Path:
    from cadalign.io import write_json

    run_dir = tmp_path / name
    write_json(run_dir / "train_config.json", record)
    return run_dir


def _seen(tiny_sim: Path, tiny_structure, out: Path, info: dict, enhance: str = "auto") -> list[np.ndarray]:
    cfg = dataclasses.replace(PRESETS["fast"], enhance=enhance, overlay=False)
    det = _Recorder()
    run(cfg, tiny_sim / "frames", det, tiny_structure.models, tiny_structure.class_names, out,
        calib=calibration_from_scene(tiny_sim / "gt" / "sim" / "000000"), detector_info=info)
    return det.images


def test_auto_prepares_frames_as_the_runs_training_images(tiny_sim: Path, tiny_structure, tmp_path: Path) -> None:
    """'auto' reads the preparation the training run recorded (here CLAHE with a non-default clip), and the
    infer record says what was applied; a run naming only its dataset gets the dataset's record."""
    from cadalign.io import read_json
    from cadalign.sfm.image_prep import write_record

    raw = [f.image for f in iter_frames(tiny_sim / "frames")]
    prep = {"enhance": "clahe", "clahe_clip": 3.0, "clahe_tiles": 4}
    run_dir = _recorded_run(tmp_path, "run", {"dataset": "/nowhere", "images": prep})
    seen = _seen(tiny_sim, tiny_structure, tmp_path / "a", {"kind": "network", "run": str(run_dir)})
    want = [enhance(f, FrameConfig(enhance="clahe", clahe_clip=3.0, clahe_tiles=4)) for f in raw]
    assert all(np.array_equal(s, w) for s, w in zip(seen, want, strict=True))
    assert not np.array_equal(want[0], enhance(raw[0], FrameConfig(enhance="clahe")))  # the clip mattered
    assert read_json(tmp_path / "a" / "timings.json")["detector"]["images"] == prep

    ds = tmp_path / "ds"
    write_record(ds, {"enhance": "clahe_wb", "clahe_clip": 2.0, "clahe_tiles": 8}, source="test")
    old_run = _recorded_run(tmp_path, "old_run", {"dataset": str(ds)})  # recorded before 'images' existed
    seen = _seen(tiny_sim, tiny_structure, tmp_path / "b", {"kind": "network", "run": str(old_run)})
    assert np.array_equal(seen[0], enhance(raw[0], FrameConfig(enhance="clahe_wb")))


def test_auto_feeds_raw_frames_to_an_oracle_or_a_run_that_says_nothing(tiny_sim: Path, tiny_structure,
                                                                       tmp_path: Path, caplog) -> None:
    raw = [f.image for f in iter_frames(tiny_sim / "frames")]
    seen = _seen(tiny_sim, tiny_structure, tmp_path / "o", {"kind": "oracle"})
    assert all(np.array_equal(s, f) for s, f in zip(seen, raw, strict=True))
    mute = _recorded_run(tmp_path, "mute", {"dataset": str(tmp_path / "gone")})
    with caplog.at_level("WARNING"):
        seen = _seen(tiny_sim, tiny_structure, tmp_path / "m", {"kind": "network", "run": str(mute)})
    assert np.array_equal(seen[0], raw[0]) and "enhance = 'clahe'" in caplog.text
    # an explicit setting wins over the run's record
    run_dir = _recorded_run(tmp_path, "run", {"images": {"enhance": "clahe", "clahe_clip": 2.0, "clahe_tiles": 8}})
    seen = _seen(tiny_sim, tiny_structure, tmp_path / "n", {"kind": "network", "run": str(run_dir)}, "none")
    assert np.array_equal(seen[0], raw[0])


def test_read_prep_finds_the_record_a_simulation_or_an_older_build(tiny_sim: Path, tmp_path: Path) -> None:
    from cadalign.errors import InputError
    from cadalign.io import write_json
    from cadalign.sfm.image_prep import RECORD, read_prep

    assert read_prep(tiny_sim / "gt" / "sim" / "000000") == {"enhance": "none"}  # a simulator's raw frames
    assert read_prep(tmp_path) is None
    build = tmp_path / "build"  # a build from before images.json: the SfM stage beside the dataset says it
    write_json(build / "dataset" / "cadalign_stage.json", {"stage": "build-dataset"})
    (build / "dataset" / "all" / "000000").mkdir(parents=True)
    write_json(build / "sfm" / "cadalign_stage.json",
               {"config": {"sfm": {"frames": {"enhance": "clahe", "clahe_clip": 2.5, "clahe_tiles": 8}}}})
    want = {"enhance": "clahe", "clahe_clip": 2.5, "clahe_tiles": 8}
    assert read_prep(build / "dataset") == want and read_prep(build / "dataset" / "all" / "000000") == want
    write_json(build / "dataset" / RECORD, {"enhance": "sepia"})
    with pytest.raises(InputError, match=r"images\.json"):
        read_prep(build / "dataset" / "all" / "000000")

"""``InferConfig.enhance``: the detector sees the frames pre-processed as the dataset build did; the overlay
and everything else see the raw frames."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from cadalign.config import ConfigError, from_dict
from cadalign.infer.pipeline import PRESETS, InferConfig
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

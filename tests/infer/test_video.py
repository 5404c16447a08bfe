"""Reading frames: folders and video files; a corrupt frame is skipped with a warning naming it."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from cadalign.errors import InputError
from cadalign.infer.video import count_frames, iter_frames
from cadalign.io import write_image


def _frames(folder: Path, n: int) -> list[Path]:
    paths = []
    for i in range(n):
        img = np.full((24, 32, 3), 40 * i, np.uint8)
        img[..., 0] = 200  # red channel marks the RGB order
        paths.append(write_image(folder / f"{i:06d}.png", img))
    return paths


def test_folder_with_a_corrupt_frame(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    paths = _frames(tmp_path, 3)
    paths[1].write_bytes(b"\x89PNG not really")
    with caplog.at_level(logging.WARNING, logger="cadalign.infer.video"):
        frames = list(iter_frames(tmp_path))
    assert [f.name for f in frames] == ["000000.png", "000002.png"]
    assert [f.index for f in frames] == [0, 2]
    assert frames[0].image.shape == (24, 32, 3) and frames[0].image[0, 0, 0] == 200
    assert any("000001.png" in r.getMessage() and "corrupt" in r.getMessage() for r in caplog.records)


def test_video_file_names_frames_like_the_folder(tmp_path: Path) -> None:
    import imageio.v2 as imageio

    path = tmp_path / "v.mp4"
    with imageio.get_writer(path, format="FFMPEG", fps=5, codec="libx264", macro_block_size=16,
                            ffmpeg_log_level="error") as w:
        for i in range(4):
            w.append_data(np.full((32, 48, 3), 60 * i, np.uint8))
    frames = list(iter_frames(path))
    assert [f.name for f in frames] == [f"{i:06d}.png" for i in range(4)]
    assert abs(int(frames[2].image.mean()) - 120) <= 3
    assert [f.name for f in iter_frames(path, stride=2, max_frames=1)] == ["000000.png"]


def test_frames_up_to_after_are_passed_over_and_not_counted(tmp_path: Path, monkeypatch) -> None:
    """A resumed run reads on after its last finished frame: those before are not decoded (a folder's) and do not
    count towards max_frames; a video's are read past."""
    import cv2
    import imageio.v2 as imageio

    paths = _frames(tmp_path / "f", 5)
    read = []
    real = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda p, *a: read.append(Path(p).name) or real(p, *a))
    frames = list(iter_frames(tmp_path / "f", after=2, max_frames=1))
    assert [f.index for f in frames] == [3] and read == ["000003.png"]
    assert [f.name for f in iter_frames(tmp_path / "f", after=1)] == [p.name for p in paths[2:]]
    assert list(iter_frames(tmp_path / "f", after=9)) == []
    path = tmp_path / "v.mp4"
    with imageio.get_writer(path, format="FFMPEG", fps=5, codec="libx264", macro_block_size=16,
                            ffmpeg_log_level="error") as w:
        for i in range(4):
            w.append_data(np.full((32, 48, 3), 60 * i, np.uint8))
    frames = list(iter_frames(path, after=1))
    assert [f.name for f in frames] == ["000002.png", "000003.png"] and abs(int(frames[0].image.mean()) - 120) <= 3
    # a progress bar's total: what iter_frames will yield
    assert count_frames(path, after=1) == 2 and count_frames(path, max_frames=1) == 1
    assert count_frames(tmp_path / "f", after=2) == 2 and count_frames(tmp_path / "f", after=9) == 0
    assert count_frames(tmp_path / "f", max_frames=3) == 3 and count_frames(tmp_path / "f") == 5
    for stride in (1, 2, 3, 4, 6):  # with a stride, and after a resumed run's last frame
        for after in (-1, 0, 1, 2, 3, 4):
            want = [f.index for f in iter_frames(tmp_path / "f", stride=stride, after=after)]
            assert count_frames(tmp_path / "f", stride=stride, after=after) == len(want), (stride, after)
            assert all(i % stride == 0 and i > after for i in want)


def test_bad_sources_raise_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        list(iter_frames(tmp_path / "missing.mp4"))
    with pytest.raises(InputError, match="holds no images"):
        list(iter_frames(tmp_path))
    bad = tmp_path / "notes.txt"
    bad.write_text("x")
    with pytest.raises(InputError, match="neither a frame folder nor a video"):
        list(iter_frames(bad))
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"garbage")
    with pytest.raises(InputError, match="could not open video"):
        list(iter_frames(broken))

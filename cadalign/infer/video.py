"""Frames from a video file, a folder of images or a ROS bag's image topic, skipping unreadable frames with a
warning naming them.

Frames are yielded as RGB uint8 arrays with a stable name: the file name for a folder, ``NNNNNN.png``
(the 0-based frame index) for a video, so a video and the folder of its frames give the same names
(``cadalign sim`` writes ``frames/NNNNNN.png`` beside ``video.mp4``); a bag's frames are named the same way
by their position on the topic (:mod:`cadalign.formats.bag`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cadalign.errors import InputError
from cadalign.formats.bag import is_bag, iter_bag_frames, resolve_topic
from cadalign.io import atomic_path
from cadalign.sfm.frames import IMAGE_SUFFIXES, VIDEO_SUFFIXES

log = logging.getLogger(__name__)

MAX_BAD_VIDEO_READS = 25
"""Consecutive failed reads after which a video counts as ended (a truncated file)."""


@dataclass(frozen=True)
class VideoFrame:
    index: int
    """0-based position in the input (counting skipped frames)."""
    name: str
    """File name (folder) or ``NNNNNN.png`` (video)."""
    image: np.ndarray
    """(H, W, 3) RGB uint8."""
    stamp_ns: int | None = None
    """Capture time in nanoseconds since the epoch (a ROS bag message's header stamp); None for videos, folders."""


def list_frames(source: Path) -> list[Path]:
    """The image files of a frame folder, sorted by name."""
    files = sorted(p for p in Path(source).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise InputError(f"{source} holds no images ({', '.join(IMAGE_SUFFIXES)}); pass a video or a frame folder")
    return files


def count_frames(source: Path, *, stride: int = 1, max_frames: int | None = None, topic: str | None = None,
                 after: int = -1) -> int | None:
    """How many frames :func:`iter_frames` will yield with the same arguments, for a progress bar's
    total: a folder's images, a video's frame count as its container gives it, a bag topic's messages (corrupt
    frames, skipped when read, still count); None when the source does not say."""
    source = Path(source)
    if is_bag(source):
        n: int | None = resolve_topic(source, topic).count
    elif source.is_dir():
        n = len(list_frames(source))
    elif source.suffix.lower() in VIDEO_SUFFIXES:
        cap = cv2.VideoCapture(str(source))
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0) or None
        cap.release()
    else:
        return None
    if n is None:
        return max_frames
    n = max((n - 1) // stride - after // stride, 0)  # indices after ``after``, up to n - 1, that stride keeps
    return n if max_frames is None else min(n, max_frames)


def iter_frames(source: Path, *, stride: int = 1, max_frames: int | None = None,
                topic: str | None = None, after: int = -1) -> Iterator[VideoFrame]:
    """Yield every ``stride``-th frame of a video file, an image folder or a ROS bag's image ``topic`` (RGB uint8).

    ``topic`` None reads a bag's only image topic; it must be None for videos and folders. ``after``: frames up to
    this index are passed over, undecoded where the source allows, and do not count towards ``max_frames`` (a
    resumed run).

    A frame that cannot be decoded is skipped with a warning naming it; the index still advances.

    Raises:
        InputError: the source is missing, not a video/folder, or cannot be opened at all.
    """
    source = Path(source)
    if not source.exists():
        raise InputError(f"video, ROS bag or frame folder not found: {source}")
    if stride < 1:
        raise InputError(f"stride must be >= 1, got {stride}")
    if is_bag(source):
        gen: Iterator[VideoFrame] = (VideoFrame(f.index, f.name, f.image, f.stamp_ns)
                                     for f in iter_bag_frames(source, topic))
    elif topic is not None:
        raise InputError(f"--topic {topic} is for ROS bags, but {source} is not one; drop --topic")
    else:
        gen = _folder(source, after) if source.is_dir() else _video(source, after)
    if max_frames is not None and max_frames <= 0:
        return
    n = 0
    for frame in gen:
        if frame.index <= after or frame.index % stride:
            continue
        n += 1
        yield frame
        if max_frames is not None and n >= max_frames:  # before the next frame is decoded
            return


def _folder(source: Path, after: int = -1) -> Iterator[VideoFrame]:
    for i, path in enumerate(list_frames(source)):
        if i <= after:
            continue
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if img is None or img.size == 0:
            log.warning("skipping corrupt frame %s (could not decode it)", path)
            continue
        yield VideoFrame(i, path.name, np.ascontiguousarray(img[..., ::-1]))


def _video(source: Path, after: int = -1) -> Iterator[VideoFrame]:
    if source.suffix.lower() not in VIDEO_SUFFIXES:
        raise InputError(f"{source} is neither a frame folder nor a video ({', '.join(VIDEO_SUFFIXES)})")
    cap = cv2.VideoCapture(str(source))
    if not cap.isOpened():
        raise InputError(f"could not open video {source}: the file is corrupt or its codec is unsupported")
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    i, bad = 0, 0
    try:
        while i <= after:  # passed over: read, not decoded (a failed read counts as in the loop below)
            if not cap.grab() and (i >= total or bad >= MAX_BAD_VIDEO_READS):
                return
            i += 1
        while True:
            ok, img = cap.read()
            if not ok or img is None:
                if i >= total or bad >= MAX_BAD_VIDEO_READS:
                    return
                log.warning("skipping corrupt frame %d (%06d.png) of %s (could not decode it)", i, i, source)
                i, bad = i + 1, bad + 1
                continue
            bad = 0
            yield VideoFrame(i, f"{i:06d}.png", np.ascontiguousarray(img[..., ::-1]))
            i += 1
    finally:
        cap.release()


def video_writer(path: Path, fps: float):  # -> imageio writer
    import imageio.v2 as imageio  # lazy: heavy dependency (imageio)

    return imageio.get_writer(path, format="FFMPEG", fps=fps, codec="libx264", quality=7, macro_block_size=16,
                              ffmpeg_log_level="error")


def overlay_piece(out_dir: Path, k: int) -> Path:
    """The ``k``-th piece of a run's overlay while the run goes on (a resumed run adds pieces)."""
    return Path(out_dir) / f"overlay.part{k}.mp4"


def overlay_pieces(out_dir: Path) -> list[Path]:
    """The overlay pieces in ``out_dir``, in order."""
    return sorted(Path(out_dir).glob("overlay.part*.mp4"), key=lambda p: int(p.stem.removeprefix("overlay.part")))


def join_overlays(pieces: list[Path], path: Path, fps: float) -> None:
    """``overlay.mp4`` from the overlay's pieces of an interrupted run and its resumption, in order; a piece a
    killed run left unreadable is left out, with a warning."""
    pieces = [p for p in pieces if p.is_file()]
    if len(pieces) == 1:
        os.replace(pieces[0], path)
        return
    if not pieces:
        return
    import imageio.v2 as imageio  # lazy: heavy dependency (imageio)

    with atomic_path(path) as tmp:
        writer = video_writer(tmp, fps)
        try:
            for p in pieces:
                try:
                    for im in imageio.get_reader(p, format="FFMPEG"):
                        writer.append_data(im)
                except (OSError, RuntimeError) as exc:
                    log.warning("%s: unreadable (%s; a killed run leaves its overlay unfinished): its frames are "
                                "missing from %s", p, str(exc).splitlines()[0], path)
        finally:
            writer.close()
    for p in pieces:
        p.unlink()

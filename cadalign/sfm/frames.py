"""Frames for SfM from a video, an image folder or a ROS bag's image topic: sampling, blur / duplicate
rejection, enhancement, masks.

The core is :func:`select_frames`, a pure generator over ``(name, image)``
candidates that keeps or rejects each one with a reason. Checks run on a grey
copy resized to ``analysis_width``:

- *blurred*: the variance of the Laplacian (a standard focus measure) is below
  ``blur_ratio`` times the median of the recent candidates (relative, so it
  adapts to murky water where every frame is soft), and the frame's verified ORB
  matches with the last kept frame are fewer than ``blur_keep_matches`` times those
  of the last two kept frames (:mod:`cadalign.sfm.blur`: a softer frame that still
  matches would register, so it is kept); or below ``min_sharpness`` (off by default);
- *near-duplicate*: the median motion of tracked corners (pyramidal Lucas-Kanade)
  since the last kept frame is below ``min_motion`` of the image diagonal; when
  too few corners can be tracked, the mean absolute grey difference is used.

:func:`extract_frames` (disk) writes the kept frames, optionally enhanced for
murky water (CLAHE, grey-world white balance), and COLMAP masks. :func:`frame_candidates` is the one
place that turns an input path (video, folder, ROS 1 ``.bag`` or ROS 2 bag folder) into frames.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from cadalign.errors import InputError
from cadalign.formats.bag import is_bag, iter_bag_frames, resolve_topic
from cadalign.io import link_or_copy, read_image, write_image
from cadalign.sfm.blur import MatchCheck
from cadalign.sfm.config import FrameConfig
from cadalign.types import Progress

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".m4v", ".webm")
_MIN_TRACKED = 12
_DIFF_DUPLICATE = 0.01  # mean |grey difference| / 255 below which a frame without corners is a duplicate
_DARK_P99 = 12  # a frame whose 99th-percentile grey level is at most this is black (lamps off, lens cap)
_BRIGHT_P1 = 243  # a frame whose 1st-percentile grey level is at least this is overexposed (washed out)



@dataclass(frozen=True)
class FrameDecision:
    """What happened to one candidate frame.

    Attributes:
        name: output file name (``000123.png`` for video frame 123, the file name for images).
        source: the video frame index or the source image path.
        kept: whether the frame goes to SfM.
        reason: why a frame was rejected ('black', 'overexposed', 'blurred', 'near-duplicate', 'max_frames');
            '' when kept.
        sharpness: variance of the Laplacian at analysis size.
        motion: median corner motion since the last kept frame (fraction of the diagonal); -1 for the first.
        matches: verified ORB matches with the last kept frame, counted only for a frame softer than
            ``blur_ratio`` of its neighbours (:mod:`cadalign.sfm.blur`); -1 when not counted.
        stamp_ns: the message's header stamp in nanoseconds since the epoch (ROS bags); None for videos and
            folders, which carry no capture time.
    """

    name: str
    source: str
    kept: bool
    reason: str
    sharpness: float
    motion: float
    stamp_ns: int | None = None
    matches: int = -1


def sharpness(gray: np.ndarray) -> float:
    """Variance of the Laplacian of an (H, W) uint8 grey image (higher is sharper)."""
    return float(cv2.Laplacian(gray, cv2.CV_64F).var())


def motion_between(prev: np.ndarray, cur: np.ndarray) -> float:
    """Median image motion from ``prev`` to ``cur`` as a fraction of the image diagonal.

    Tracks Shi-Tomasi corners with pyramidal Lucas-Kanade; falls back to the mean
    absolute difference (scaled so that ``_DIFF_DUPLICATE`` maps to a tiny motion)
    when fewer than ``_MIN_TRACKED`` corners survive (textureless water).

    Args:
        prev: (H, W) uint8 grey image.
        cur: (H, W) uint8 grey image of the same size.
    """
    h, w = prev.shape
    diag = float(np.hypot(h, w))
    pts = cv2.goodFeaturesToTrack(prev, maxCorners=300, qualityLevel=0.01, minDistance=max(3, w // 64))
    if pts is not None and len(pts) >= _MIN_TRACKED:
        nxt, status, _ = cv2.calcOpticalFlowPyrLK(prev, cur, pts, None, winSize=(21, 21), maxLevel=3)
        ok = status.ravel() == 1
        if ok.sum() >= _MIN_TRACKED:
            return float(np.median(np.linalg.norm((nxt - pts)[ok].reshape(-1, 2), axis=1)) / diag)
    diff = float(np.mean(np.abs(prev.astype(np.float32) - cur.astype(np.float32))) / 255.0)
    return 0.0 if diff < _DIFF_DUPLICATE else 1.0


def _analysis_gray(image: np.ndarray, width: int) -> np.ndarray:
    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    if gray.dtype != np.uint8:
        raise InputError(f"frames must be 8-bit, got {gray.dtype}; convert the video or images to 8-bit")
    if gray.shape[1] > width:
        h = max(1, round(gray.shape[0] * width / gray.shape[1]))
        gray = cv2.resize(gray, (width, h), interpolation=cv2.INTER_AREA)
    return gray


def exposure_problem(gray: np.ndarray) -> str:
    """'black' or 'overexposed' when an (H, W) uint8 grey frame carries (almost) no image, else ''."""
    p1, p99 = np.percentile(gray, (1, 99))
    if p99 <= _DARK_P99:
        return "black"
    if p1 >= _BRIGHT_P1:
        return "overexposed"
    return ""


def _check_frame(rgb: object, name: str, source: str, first: tuple[str, tuple[int, ...]] | None) -> None:
    """Refuse a frame that is not an (H, W[, C]) image or whose size differs from the first frame's."""
    if not isinstance(rgb, np.ndarray) or rgb.ndim not in (2, 3) or min(rgb.shape[:2], default=0) < 2:
        shape = getattr(rgb, "shape", None)
        raise InputError(f"frame {name} ({source}) is not an image (shape {shape}); remove or replace it")
    if first is not None and rgb.shape[:2] != first[1]:
        h, w = rgb.shape[:2]
        raise InputError(
            f"frames of mixed sizes: {name} ({source}) is {w}x{h} but {first[0]} is {first[1][1]}x{first[1][0]}; "
            "SfM uses one camera for all frames - resize them to one size or split the input by camera")


def select_frames(
    candidates: Iterable[tuple[str, str, np.ndarray]], cfg: FrameConfig
) -> Iterator[tuple[FrameDecision, np.ndarray]]:
    """Decide for each candidate ``(name, source, rgb)`` whether it goes to SfM; yields (decision, rgb).

    Pure apart from reading the iterator: the same candidates and config always give the same
    decisions. Black and overexposed frames (see :func:`exposure_problem`) are rejected first; blur
    is judged against the median sharpness of the last ``blur_window`` usable candidates (causal) and, for a
    softer frame, against the matches of the last kept frames (:class:`~cadalign.sfm.blur.MatchCheck`),
    duplicates against the last kept frame; in 'motion' sampling a frame is kept only once the motion
    reaches ``keyframe_motion``.

    Raises:
        InputError: a candidate is not an image, or its size differs from the first candidate's.
    """
    recent: deque[float] = deque(maxlen=cfg.blur_window)
    last_kept: np.ndarray | None = None
    first: tuple[str, tuple[int, ...]] | None = None
    n_kept = 0
    check = MatchCheck(cfg.blur_keep_matches)
    min_motion = cfg.keyframe_motion if cfg.sampling == "motion" else cfg.min_motion
    for candidate in candidates:
        name, source, rgb = candidate[:3]
        stamp = candidate[3] if len(candidate) > 3 else None
        _check_frame(rgb, name, source, first)
        first = first or (name, rgb.shape[:2])
        gray = _analysis_gray(rgb, cfg.analysis_width)
        exposure = exposure_problem(gray)
        if exposure:
            yield FrameDecision(name, source, False, exposure, sharpness(gray), -1.0, stamp), rgb
            continue
        sharp = sharpness(gray)
        reference = float(np.median(recent)) if recent else sharp
        recent.append(sharp)
        motion = -1.0 if last_kept is None else motion_between(last_kept, gray)
        matches = -1
        soft = cfg.blur_ratio > 0 and sharp < cfg.blur_ratio * reference
        if soft and not (cfg.max_frames and n_kept >= cfg.max_frames):
            keep_soft, matches = check.matches_enough(gray)
            soft = not keep_soft
        if cfg.max_frames and n_kept >= cfg.max_frames:
            reason = "max_frames"
        elif sharp < cfg.min_sharpness or soft:
            reason = "blurred"
        elif motion >= 0 and min_motion > 0 and motion < min_motion:
            reason = "near-duplicate"
        else:
            reason = ""
        if not reason:
            last_kept = gray
            check.kept(gray)
            n_kept += 1
        yield FrameDecision(name, source, not reason, reason, sharp, motion, stamp, matches), rgb


def enhance(rgb: np.ndarray, cfg: FrameConfig) -> np.ndarray:
    """Pre-process an (H, W, 3) uint8 RGB frame for murky water (see ``FrameConfig.enhance``)."""
    if cfg.enhance == "none":
        return rgb
    out = rgb
    if cfg.enhance == "clahe_wb":
        means = out.reshape(-1, 3).astype(np.float64).mean(0)
        gains = means.mean() / np.maximum(means, 1.0)
        out = np.clip(out.astype(np.float32) * gains.astype(np.float32), 0, 255).astype(np.uint8)
    lab = cv2.cvtColor(out, cv2.COLOR_RGB2LAB)
    clahe = cv2.createCLAHE(clipLimit=cfg.clahe_clip, tileGridSize=(cfg.clahe_tiles, cfg.clahe_tiles))
    lab[..., 0] = clahe.apply(np.ascontiguousarray(lab[..., 0]))
    return cv2.cvtColor(lab, cv2.COLOR_LAB2RGB)


def is_video(path: Path) -> bool:
    return Path(path).is_file() and Path(path).suffix.lower() in VIDEO_SUFFIXES


def list_images(folder: Path) -> list[Path]:
    """The images of a folder, sorted by name (the capture order of a frame dump)."""
    files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not files:
        raise InputError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}; pass a video or a frames folder")
    return files


def video_candidates(path: Path, cfg: FrameConfig) -> tuple[Iterator[tuple[str, str, np.ndarray]], int]:
    """Candidate frames of a video (OpenCV) and their expected count."""
    if Path(path).stat().st_size == 0:
        raise InputError(f"video {path} is empty (0 bytes); re-copy or re-export the recording")
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise InputError(f"could not open video {path}: the file is corrupt or its codec is not supported by "
                         "OpenCV; re-encode it (e.g. ffmpeg -i IN -c:v libx264 OUT.mp4) or extract frames to a "
                         "folder first")
    fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
    total = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
    step = max(1, round(fps / cfg.fps)) if cfg.sampling == "fps" and fps > 0 else 1

    def gen() -> Iterator[tuple[str, str, np.ndarray]]:
        index = 0
        try:
            while True:
                if index % step:
                    if not cap.grab():
                        break
                else:
                    ok, bgr = cap.read()
                    if not ok:
                        break
                    yield f"{index:06d}.png", str(index), np.ascontiguousarray(bgr[..., ::-1])
                index += 1
        finally:
            cap.release()

    return gen(), (total + step - 1) // step if total > 0 else 0


def folder_candidates(folder: Path) -> tuple[Iterator[tuple[str, str, np.ndarray]], int]:
    files = list_images(folder)
    return ((p.name, str(p), read_image(p)) for p in files), len(files)


def bag_candidates(path: Path, topic: str | None) -> tuple[Iterator[tuple[str, str, np.ndarray, int]], int]:
    """Candidate frames of a ROS bag's image topic ``(name, "topic#index", rgb, stamp_ns)`` and their count."""

    chosen = resolve_topic(path, topic)
    frames = iter_bag_frames(path, chosen.name)
    return ((f.name, f"{chosen.name}#{f.index}", f.image, f.stamp_ns) for f in frames), chosen.count


def frame_candidates(source: Path, cfg: FrameConfig, topic: str | None = None
                     ) -> tuple[Iterator[tuple[str, str, np.ndarray] | tuple[str, str, np.ndarray, int]], int]:
    """Candidate frames ``(name, source, rgb[, stamp_ns])`` of any input and their expected count.

    ``source`` is a video file, a folder of images, a ROS 1 ``.bag`` or a ROS 2 bag folder; ``topic`` picks
    the bag's image topic (None: its only one) and must be None for other inputs.

    Raises:
        InputError: the input is missing or of no known kind, or a topic is given for a non-bag, or the
            topic is missing from the bag (naming its image topics).
    """
    source = Path(source)
    if is_bag(source):
        return bag_candidates(source, topic)
    if topic is not None and source.exists():
        raise InputError(f"--topic {topic} is for ROS bags, but {source} is not one (a .bag file or a ROS 2 bag "
                         "folder with metadata.yaml); drop --topic")
    if is_video(source):
        return video_candidates(source, cfg)
    if source.is_dir():
        return folder_candidates(source)
    if source.exists():
        raise InputError(f"{source} is neither a video ({', '.join(VIDEO_SUFFIXES)}), a ROS bag (.bag, or a ROS 2 "
                         "bag folder) nor a folder of images")
    raise InputError(f"input not found: {source}; pass an existing video ({', '.join(VIDEO_SUFFIXES)}), ROS bag "
                     "or folder of frames")


def _load_mask(cfg: FrameConfig, name: str, shape: tuple[int, int]) -> np.ndarray | None:
    """The (H, W) bool mask of frame ``name`` (True = use), or None when no mask is configured."""
    if cfg.mask is None and not cfg.mask_rects:
        return None
    mask = np.ones(shape, bool)
    if cfg.mask is not None:
        path = Path(cfg.mask)
        if path.is_dir():
            stem = Path(name).stem
            hits = [p for p in (path / name, path / f"{name}.png", path / f"{stem}.png") if p.is_file()]
            path = hits[0] if hits else None
        if path is not None:
            img = read_image(path, unchanged=True)
            img = img if img.ndim == 2 else img[..., 0]
            if img.shape != shape:
                raise InputError(f"mask {path} is {img.shape[1]}x{img.shape[0]} but frame {name} is "
                                 f"{shape[1]}x{shape[0]}; resize the mask to the frame size")
            mask &= img > 0
    for x, y, w, h in cfg.mask_rects:
        mask[max(0, y) : max(0, y + h), max(0, x) : max(0, x + w)] = False
    return mask


def first_frame_size(source: Path) -> tuple[int, int]:
    """``(width, height)`` of the first frame of a video or image folder (to check a calibration against).

    Raises:
        InputError: the source is missing, unreadable or holds no frame.
    """
    source = Path(source)
    if is_video(source):
        candidates, _ = video_candidates(source, FrameConfig(sampling="all"))
    elif source.is_dir():
        candidates, _ = folder_candidates(source)
    else:
        raise InputError(f"input not found: {source}; pass a video ({', '.join(VIDEO_SUFFIXES)}) or a folder of frames")
    for _, _, rgb in candidates:
        return int(rgb.shape[1]), int(rgb.shape[0])
    raise InputError(f"{source}: no frame could be decoded; check the input")


def extract_frames(
    source: Path, cfg: FrameConfig, images_dir: Path, masks_dir: Path, progress: Progress | None = None,
    undistort: Callable[[np.ndarray], np.ndarray] | None = None,
    topic: str | None = None,
) -> list[FrameDecision]:
    """Select frames of ``source`` (see :func:`frame_candidates`) and write them to ``images_dir``.

    Kept frames are written as PNG (undistorted by ``undistort`` when given, then enhanced per ``cfg.enhance``)
    under their decision name; masks, when configured, go to ``masks_dir/<name>.png`` (COLMAP's layout:
    255 = use, 0 = ignore). Frame selection looks at the frames as recorded.

    Raises:
        InputError: the source is missing, not a video, bag or folder of images, or yields no usable frame.
    """
    source = Path(source)
    candidates, total = frame_candidates(source, cfg, topic)
    copy_files = source.is_dir() and not is_bag(source)
    decisions: list[FrameDecision] = []
    stream = select_frames(candidates, cfg)
    for decision, rgb in progress(stream, "frames", total) if progress else stream:
        decisions.append(decision)
        if not decision.kept:
            continue
        if cfg.enhance == "none" and copy_files and undistort is None:
            link_or_copy(Path(decision.source), images_dir / decision.name)  # lossless, keeps EXIF
        else:
            write_image(images_dir / decision.name, enhance(undistort(rgb) if undistort else rgb, cfg))
        mask = _load_mask(cfg, decision.name, rgb.shape[:2])
        if mask is not None:
            write_image(masks_dir / f"{decision.name}.png", mask.astype(np.uint8) * 255)
    if not decisions:
        raise InputError(f"{source}: no frame could be decoded (a zero-length or corrupt video); check that it "
                         "plays, re-encode it (e.g. ffmpeg -i IN -c:v libx264 OUT.mp4) or extract frames to a folder")
    _warn_exposure(source, decisions)
    kept = [d for d in decisions if d.kept]
    if len(kept) < 2:
        exposure = _exposure_names(decisions)
        hint = ("check the lamps and the camera exposure of the input" if exposure else
                "lower frames.blur_ratio / frames.min_motion or check the input")
        raise InputError(f"{source}: only {len(kept)} of {len(decisions)} frames are usable "
                         f"({_count_reasons(decisions)}{exposure}); {hint}")
    log.info("frames: kept %d of %d (%s)", len(kept), len(decisions), _count_reasons(decisions) or "none rejected")
    return decisions


def _exposure_names(decisions: list[FrameDecision]) -> str:
    """'; black: a.png, b.png; overexposed: ...' (first few names per reason), or ''."""
    parts = []
    for reason in ("black", "overexposed"):
        names = [d.name for d in decisions if d.reason == reason]
        if names:
            more = f" and {len(names) - 5} more" if len(names) > 5 else ""
            parts.append(f"{reason}: {', '.join(names[:5])}{more}")
    return "; " + "; ".join(parts) if parts else ""


def _warn_exposure(source: Path, decisions: list[FrameDecision]) -> None:
    names = _exposure_names(decisions)
    if names:
        log.warning("%s: skipped frames with no usable image (lamps off / lens cap / washed out)%s", source, names)


def _count_reasons(decisions: list[FrameDecision]) -> str:
    counts: dict[str, int] = {}
    for d in decisions:
        if not d.kept:
            counts[d.reason] = counts.get(d.reason, 0) + 1
    return ", ".join(f"{n} {r}" for r, n in sorted(counts.items()))

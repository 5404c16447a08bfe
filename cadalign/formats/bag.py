"""ROS 1 and ROS 2 bags as a frame source: the image topics of a bag and their frames with timestamps.

A *bag* is a ROS 1 ``.bag`` file or a ROS 2 bag folder (``metadata.yaml`` beside ``.db3`` / ``.mcap``
files; a ``.db3`` / ``.mcap`` file inside such a folder names the folder). Both are read with the
pure-Python `rosbags <https://gitlab.com/ternaris/rosbags>`_ library (no ROS install needed).

Image topics carry ``sensor_msgs/Image`` (raw: rgb8, bgr8, rgba8, bgra8, mono8, mono16, bayer_*, 16UC1 ...;
decoded by ``rosbags-image``) or ``sensor_msgs/CompressedImage`` (jpeg / png; decoded by OpenCV). Every
frame comes out as (H, W, 3) RGB uint8: grey frames are repeated to three channels, and 16-bit frames are
shifted right by as many bits as the frame's largest value needs beyond 8 (a 12-bit camera in a 16-bit
container keeps its contrast), which is per frame and only ever a power of two.

Frames are named ``NNNNNN.png`` by their 0-based position on the topic (as a video's frames and as
``cadalign sim``'s ``frames/`` folder are), and carry the message's ``header.stamp`` in nanoseconds
(the bag's receive time when the header stamp is zero).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from cadalign.errors import InputError

log = logging.getLogger(__name__)

BAG_SUFFIXES = (".bag", ".db3", ".mcap")
"""A ROS 1 bag file, or a file of a ROS 2 bag folder (which then names its folder)."""
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
"""Message types read as frames (rosbags spells ROS 1's ``sensor_msgs/Image`` the ROS 2 way)."""
MAX_BAD_MESSAGES = 25
"""Consecutive undecodable image messages after which a topic counts as broken (not merely a bad frame)."""


@dataclass(frozen=True)
class ImageTopic:
    """One image topic of a bag."""

    name: str
    """The topic, e.g. ``/camera/image_raw``."""
    msgtype: str
    """``sensor_msgs/msg/Image`` or ``sensor_msgs/msg/CompressedImage``."""
    count: int
    """Messages on the topic."""


@dataclass(frozen=True)
class BagFrame:
    """One decoded image message."""

    index: int
    """0-based position on the topic (counting undecodable messages)."""
    name: str
    """``NNNNNN.png`` from ``index``."""
    stamp_ns: int
    """``header.stamp`` in nanoseconds since the epoch (the bag's receive time when the stamp is 0)."""
    image: np.ndarray
    """(H, W, 3) RGB uint8."""


def bag_root(path: Path) -> Path | None:
    """The bag that ``path`` names (a ``.bag`` file or a ROS 2 bag folder), or None when it is not a bag."""
    path = Path(path)
    if path.is_file() and path.suffix.lower() == ".bag":
        return path
    if path.is_file() and path.suffix.lower() in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    if path.is_dir() and (path / "metadata.yaml").is_file():
        return path
    return None


def is_bag(path: Path) -> bool:
    """Whether ``path`` is a ROS 1 bag file or a ROS 2 bag folder (or a file in one)."""
    return bag_root(path) is not None


def _reader(path: Path) -> Any:
    """An open-able ``rosbags.highlevel.AnyReader`` of the bag at ``path`` (errors name the file and the fix)."""
    root = bag_root(path)
    if root is None:
        raise InputError(f"{path} is not a ROS bag: pass a ROS 1 .bag file or a ROS 2 bag folder (with "
                         "metadata.yaml)")
    try:
        from rosbags.highlevel import AnyReader  # lazy: heavy dependency (rosbags)
    except ImportError as exc:  # optional at import time so the rest of cadalign works without it
        raise InputError(f"reading {path} needs the 'rosbags' package: pip install rosbags rosbags-image") from exc
    return AnyReader([root])


def _open(reader: Any, path: Path) -> None:
    from rosbags.highlevel import AnyReaderError  # lazy: heavy dependency (rosbags)

    try:
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError, EOFError) as exc:
        raise InputError(f"could not read ROS bag {path}: {exc}. The file is corrupt or truncated (a recording "
                         "cut off before it was closed); re-copy it, or for ROS 1 run 'rosbag reindex' on it "
                         "(ROS 2: 'ros2 bag reindex')") from None


def image_topics(path: Path) -> list[ImageTopic]:
    """The image topics of the bag at ``path``, sorted by name.

    Raises:
        InputError: not a bag, the bag is corrupt, or ``rosbags`` is not installed.
    """
    reader = _reader(path)
    _open(reader, path)
    try:
        counts: dict[tuple[str, str], int] = {}
        for c in reader.connections:
            if c.msgtype in IMAGE_TYPES:
                counts[(c.topic, c.msgtype)] = counts.get((c.topic, c.msgtype), 0) + c.msgcount
        return [ImageTopic(t, m, n) for (t, m), n in sorted(counts.items())]
    finally:
        reader.close()


def describe_topics(topics: list[ImageTopic]) -> str:
    """``/a (sensor_msgs/msg/Image, 120 messages), /b (...)`` for error messages and listings."""
    return ", ".join(f"{t.name} ({t.msgtype}, {t.count} messages)" for t in topics) or "none"


def resolve_topic(path: Path, topic: str | None) -> ImageTopic:
    """The image topic to read: ``topic``, or the only image topic of the bag when ``topic`` is None.

    Raises:
        InputError: the topic is not in the bag or carries no images, or there is no / more than one image
            topic and none was named (the message lists the image topics and says how to pick one).
    """
    topics = image_topics(path)
    if topic is None:
        if len(topics) == 1:
            return topics[0]
        if not topics:
            raise InputError(f"ROS bag {path} has no image topic (sensor_msgs/Image or CompressedImage); "
                             "record the camera topic, or pass a video or a folder of frames")
        raise InputError(f"ROS bag {path} has {len(topics)} image topics: {describe_topics(topics)}; pick one "
                         f"with --topic, e.g. --topic {topics[0].name}")
    hits = [t for t in topics if t.name == topic]
    if not hits:
        raise InputError(f"topic {topic} is not an image topic of ROS bag {path}; its image topics: "
                         f"{describe_topics(topics)} (list them with 'cadalign bag topics {path}')")
    return hits[0]


def iter_bag_frames(path: Path, topic: str | None = None) -> Iterator[BagFrame]:
    """Decode the images of ``topic`` (or of the bag's only image topic) in recording order.

    An undecodable message is skipped with a warning naming its index; its index is not reused.

    Raises:
        InputError: see :func:`resolve_topic`; or the bag breaks while reading (corrupt chunk), or more
            than :data:`MAX_BAD_MESSAGES` messages in a row cannot be decoded.
    """
    chosen = resolve_topic(path, topic)
    reader = _reader(path)
    _open(reader, path)
    try:
        conns = [c for c in reader.connections if c.topic == chosen.name and c.msgtype == chosen.msgtype]
        bad = 0
        messages = reader.messages(connections=conns)
        index = 0
        while True:
            try:
                conn, t_recv, raw = next(messages)
            except StopIteration:
                return
            except Exception as exc:  # noqa: BLE001 - rosbags raises many types on a broken chunk
                raise InputError(f"ROS bag {path} breaks after message {index} of {chosen.name}: {exc}; the file "
                                 "is corrupt or truncated - re-copy it or reindex it (rosbag reindex)") from None
            try:
                msg = reader.deserialize(raw, conn.msgtype)
                image = decode_image(msg)
            except (InputError, ValueError, KeyError, IndexError, TypeError) as exc:
                bad += 1
                log.warning("skipping undecodable image message %d of %s in %s: %s", index, chosen.name, path, exc)
                if bad >= MAX_BAD_MESSAGES:
                    raise InputError(f"ROS bag {path}: {bad} image messages in a row on {chosen.name} cannot be "
                                     f"decoded (last: {exc}); check the topic's encoding") from None
                index += 1
                continue
            bad = 0
            stamp = msg.header.stamp
            stamp_ns = int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec) or int(t_recv)
            yield BagFrame(index, f"{index:06d}.png", stamp_ns, image)
            index += 1
    finally:
        reader.close()


def decode_image(msg: Any) -> np.ndarray:
    """A ``sensor_msgs`` Image or CompressedImage message as (H, W, 3) RGB uint8 (see the module doc).

    Raises:
        InputError: an unsupported encoding or data that does not decode.
    """

    if hasattr(msg, "format"):  # CompressedImage
        img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise InputError(f"compressed image ({msg.format}) does not decode")
        img = _to_8bit(img)
        if img.ndim == 2:
            return np.ascontiguousarray(np.repeat(img[..., None], 3, axis=2))
        code = cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB
        return np.ascontiguousarray(cv2.cvtColor(img, code))
    from rosbags.image import ImageError, image_to_cvimage  # lazy: heavy dependency (rosbags)
    from rosbags.image.image import convert_color  # lazy: heavy dependency (rosbags)

    enc = str(msg.encoding)
    expected = int(msg.step) * int(msg.height)
    if len(msg.data) < expected:
        raise InputError(f"image message holds {len(msg.data)} bytes, its header says {expected}")
    try:
        img = image_to_cvimage(msg)
        if img.dtype != np.uint8:
            img = _to_8bit(img)
            enc = "mono8" if img.ndim == 2 else "rgb8" if enc.lower().startswith("rgb") else "bgr8"
        rgb = img if enc in ("rgb8", "mono8", "8UC1") else convert_color(img, enc, "rgb8")
    except (ImageError, ValueError, TypeError) as exc:
        raise InputError(f"image encoding {enc!r}: {exc}") from None
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[..., None], 3, axis=2)
    return np.ascontiguousarray(rgb[..., :3])


def _to_8bit(img: np.ndarray) -> np.ndarray:
    """8-bit from 16-bit (or wider) by a right shift that keeps the frame's largest value (module doc)."""
    if img.dtype == np.uint8:
        return img
    if img.dtype.kind == "f":
        return np.clip(img * 255.0, 0, 255).astype(np.uint8)
    top = int(img.max(initial=0))
    shift = max(0, top.bit_length() - 8)
    return (img.astype(np.uint64) >> shift).astype(np.uint8)

"""Write ROS 1 / ROS 2 bags of image frames with ``rosbags`` (the inputs of the bag tests)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

T0_NS = 1_700_000_000_000_000_000
"""The first frame's header stamp (a fixed date, so stamps are exact and comparable)."""
DT_NS = 100_000_000
"""10 frames/s."""


def _message(typestore: object, rgb: np.ndarray, k: int, encoding: str, compressed: bool) -> object:
    """A sensor_msgs Image (``encoding``: rgb8, bgr8, mono8 or mono16) or CompressedImage (png) of ``rgb``."""
    Header = typestore.types["std_msgs/msg/Header"]
    Time = typestore.types["builtin_interfaces/msg/Time"]
    stamp = T0_NS + k * DT_NS
    extra = {"seq": k} if "seq" in Header.__dataclass_fields__ else {}  # ROS 1's Header has a sequence number
    header = Header(stamp=Time(sec=stamp // 10**9, nanosec=stamp % 10**9), frame_id="camera", **extra)
    if compressed:
        ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
        assert ok
        return typestore.types["sensor_msgs/msg/CompressedImage"](header=header, format="png",
                                                                 data=np.frombuffer(buf.tobytes(), np.uint8))
    if encoding == "rgb8":
        arr = rgb
    elif encoding == "bgr8":
        arr = rgb[..., ::-1]
    elif encoding == "mono8":
        arr = rgb[..., 0]
    elif encoding == "mono16":
        arr = (rgb[..., 0].astype(np.uint16) << 4).astype(">u2")  # a 12-bit camera, big-endian on the wire
    else:
        raise ValueError(encoding)
    arr = np.ascontiguousarray(arr)
    h, w = arr.shape[:2]
    return typestore.types["sensor_msgs/msg/Image"](
        header=header, height=h, width=w, encoding=encoding, is_bigendian=int(encoding == "mono16"),
        step=arr.strides[0], data=np.frombuffer(arr.tobytes(), np.uint8))


def write_bag(frames: list[np.ndarray], path: Path, *, ros: int, topic: str = "/camera/image_raw",
              encoding: str = "rgb8", compressed: bool = False, storage: str = "sqlite3",
              other_topics: tuple[str, ...] = ()) -> Path:
    """A bag at ``path`` (ROS 1 file, or ROS 2 folder) with ``frames`` (RGB uint8) on ``topic``, stamped
    ``T0_NS + k * DT_NS``; ``other_topics`` get the same frames (a second camera)."""
    from rosbags.typesys import Stores, get_typestore

    kind = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"
    if ros == 1:
        from rosbags.rosbag1 import Writer

        typestore = get_typestore(Stores.ROS1_NOETIC)
        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        typestore = get_typestore(Stores.ROS2_HUMBLE)
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(path, version=9, storage_plugin=plugin)
    with writer:
        conns = [writer.add_connection(t, kind, typestore=typestore) for t in (topic, *other_topics)]
        for k, rgb in enumerate(frames):
            msg = _message(typestore, rgb, k, encoding, compressed)
            data = typestore.serialize_ros1(msg, kind) if ros == 1 else typestore.serialize_cdr(msg, kind)
            for conn in conns:
                writer.write(conn, T0_NS + k * DT_NS + 5_000_000, data)
    return path

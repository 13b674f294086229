"""rosbag2 files of camera images, written and read with rosbags (no rosbag2_py wheel exists).

Writing turns a scene folder into what a camera driver records: sensor_msgs/Image (or, with
``compression``, sensor_msgs/CompressedImage PNG or JPEG on ``<topic>/compressed``, as
image_transport records it) plus a CameraInfo with the same header (frame
``camera_optical_frame``, identical stamps) at a fixed rate. Reading accepts any rosbag2 (or
ROS 1 bag) with Image or CompressedImage topics and pairs every image with the CameraInfo of
the same stamp, so the estimator can run on recorded data. Every image is bounded in pixels
before it is decoded (``image_codec``).
"""
from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag2 import StoragePlugin, Writer, WriterError
from rosbags.typesys import Stores, get_typestore

from ..camera import Camera, CameraError
from ..image_codec import (MAX_IMAGE_PIXELS, camera_from_info, decode_compressed, decode_image, encode_compressed,
                           encode_image, read_image_file)
from ..scene_folder import load_scene

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
COMPRESSIONS = ("png", "jpeg")
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
FRAME_ID = "camera_optical_frame"
#: First stamp of a written bag (2024-01-01T00:00:00Z): fixed, so bags are reproducible.
START_NS = 1_704_067_200 * 10**9
STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}


class BagError(ValueError):
    """A bag that cannot be written or read as camera images, with the reason."""


@dataclass
class Frame:
    """One image of a bag with its header and the camera of the matching CameraInfo (None
    if the bag has no CameraInfo)."""

    stamp_ns: int
    frame_id: str
    image: np.ndarray
    camera: Camera | None
    #: (format, bytes) of a CompressedImage as recorded, to replay it unchanged
    compressed: tuple[str, bytes] | None = None


def write_bag(bag: str | Path, images: Iterable[np.ndarray], camera: Camera, *,
              storage: str = "mcap", topic: str = "/camera/image_raw",
              info_topic: str = "/camera/camera_info", rate: float = 10.0,
              frame_id: str = FRAME_ID, start_ns: int = START_NS, compression: str | None = None) -> int:
    """Write images (grey or BGR arrays) and one CameraInfo per image; returns the count.

    ``compression`` ``png`` or ``jpeg`` writes CompressedImage messages on
    ``<topic>/compressed`` instead of Image messages on ``topic``.
    """
    if storage not in STORAGES:
        raise BagError(f"unknown storage {storage!r}; choose {' or '.join(STORAGES)}")
    if compression not in (None, *COMPRESSIONS):
        raise BagError(f"unknown compression {compression!r}; choose {' or '.join(COMPRESSIONS)}")
    if not 0 < rate <= 1e6:  # also refuses NaN; a million frames per second is no camera
        raise BagError(f"rate must be in (0, 1e6] frames per second, got {rate}")
    store = get_typestore(Stores.ROS2_KILTED)
    types = store.types
    count = 0
    try:
        with Writer(bag, version=9, storage_plugin=STORAGES[storage]) as writer:
            msgtype = COMPRESSED_IMAGE if compression else IMAGE
            image_conn = writer.add_connection(topic + ("/compressed" if compression else ""), msgtype,
                                               typestore=store)
            info_conn = writer.add_connection(info_topic, CAMERA_INFO, typestore=store)
            for count, image in enumerate(images, start=1):
                stamp = start_ns + round((count - 1) * 1e9 / rate)
                header = types["std_msgs/msg/Header"](
                    stamp=types["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9),
                    frame_id=frame_id)
                if compression:
                    fmt, data = encode_compressed(image, compression)
                    msg = types[COMPRESSED_IMAGE](header=header, format=fmt, data=np.frombuffer(data, np.uint8))
                else:
                    encoding, step, data = encode_image(image)
                    msg = types[IMAGE](header=header, height=image.shape[0], width=image.shape[1],
                                       encoding=encoding, is_bigendian=0, step=step,
                                       data=np.frombuffer(data, dtype=np.uint8))
                info = _camera_info(types, camera, header)
                writer.write(info_conn, stamp, store.serialize_cdr(info, CAMERA_INFO))
                writer.write(image_conn, stamp, store.serialize_cdr(msg, msgtype))
    except (WriterError, ValueError) as exc:
        raise BagError(f"cannot write bag {bag}: {exc}") from None
    return count


def _camera_info(types, camera: Camera, header):
    """CameraInfo of a camera (no rectification: P = [K | 0])."""
    K = camera.K
    P = np.hstack([K, np.zeros((3, 1))])
    return types[CAMERA_INFO](
        header=header, height=camera.height, width=camera.width, distortion_model="plumb_bob",
        d=np.asarray(camera.dist_coeffs, dtype=float), k=K.reshape(-1), r=np.eye(3).reshape(-1),
        p=P.reshape(-1), binning_x=0, binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                      do_rectify=False))


def write_scene_bag(scene: str | Path, bag: str | Path, **options) -> int:
    """Write the images of a scene folder, in gt.json order, with its camera (see write_bag)."""
    loaded = load_scene(scene)

    def images():
        for entry in loaded.entries:
            try:
                yield read_image_file(entry.path)
            except ValueError as exc:
                raise BagError(str(exc)) from None

    return write_bag(bag, images(), loaded.camera, **options)


def read_bag(bag: str | Path, topic: str | None = None, info_topic: str | None = None,
             max_pixels: int = MAX_IMAGE_PIXELS) -> Iterator[Frame]:
    """Frames of an Image or CompressedImage topic in recording order, each with its camera.

    ``topic`` defaults to the bag's only image topic; ``info_topic`` to the CameraInfo
    topic beside it (same namespace; for ``.../image_raw/compressed`` beside
    ``.../image_raw``), else the bag's only one. A frame gets the camera of the CameraInfo
    with its stamp, else of the latest one before it, else the first.
    """
    path = Path(bag)
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_KILTED)) as reader:
            image_conns, info_conns = _select(reader, path, topic, info_topic)
            cameras = _cameras(reader, info_conns)
            stamps = sorted(cameras)
            for index, (conn, _, raw) in enumerate(reader.messages(connections=image_conns)):
                msg = reader.deserialize(raw, conn.msgtype)
                stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
                compressed = None
                try:
                    if conn.msgtype == COMPRESSED_IMAGE:
                        compressed = (msg.format, bytes(msg.data))
                        image = decode_compressed(compressed[1], max_pixels)
                    else:
                        image = decode_image(msg.encoding, msg.height, msg.width, msg.step, msg.data,
                                             bool(msg.is_bigendian), max_pixels)
                except ValueError as exc:
                    raise BagError(f"{path}: image {index} on {conn.topic}: {exc}") from None
                yield Frame(stamp, msg.header.frame_id, image, _camera_at(cameras, stamps, stamp), compressed)
    except (AnyReaderError, OSError, CameraError) as exc:
        raise BagError(f"cannot read bag {path}: {exc}") from None
    except BagError:
        raise
    except Exception as exc:  # rosbags' storage back ends raise their own types on damaged files
        raise BagError(f"cannot read bag {path}: {type(exc).__name__}: {exc}") from None


def _select(reader: AnyReader, path: Path, topic: str | None, info_topic: str | None):
    """The connections of the chosen Image topic and of its CameraInfo topic."""
    by_type: dict[str, set[str]] = {}
    for conn in reader.connections:
        by_type.setdefault(conn.msgtype, set()).add(conn.topic)
    images = sorted(set().union(*(by_type.get(t, set()) for t in IMAGE_TYPES)))
    infos = sorted(by_type.get(CAMERA_INFO, ()))
    if not images:
        found = ", ".join(f"{c.topic} ({c.msgtype})" for c in reader.connections) or "nothing"
        raise BagError(f"{path} has no {IMAGE} or {COMPRESSED_IMAGE} topic (found: {found})")
    if topic is None:
        if len(images) > 1:
            raise BagError(f"{path} has several image topics ({', '.join(images)}); choose one")
        topic = images[0]
    elif topic not in images:
        raise BagError(f"{path} has no image topic {topic} (image topics: {', '.join(images)})")
    if info_topic is None:
        beside = topic.removesuffix("/compressed").rsplit("/", 1)[0] + "/camera_info"
        info_topic = beside if beside in infos else (infos[0] if len(infos) == 1 else None)
    elif info_topic not in infos:
        raise BagError(f"{path} has no CameraInfo topic {info_topic} "
                       f"(CameraInfo topics: {', '.join(infos) or 'none'})")
    image_conns = [c for c in reader.connections if c.topic == topic]
    return image_conns, [c for c in reader.connections if info_topic and c.topic == info_topic]


def _cameras(reader: AnyReader, connections) -> dict[int, Camera]:
    """Camera per CameraInfo stamp (CameraInfo messages are small: read them all first)."""
    cameras = {}
    if connections:
        for conn, _, raw in reader.messages(connections=connections):
            msg = reader.deserialize(raw, conn.msgtype)
            cameras[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec] = camera_from_info(msg)
    return cameras


def _camera_at(cameras: dict[int, Camera], stamps: list[int], stamp: int) -> Camera | None:
    if not stamps:
        return None
    return cameras[stamps[max(bisect_right(stamps, stamp) - 1, 0)]]

"""numpy <-> sensor_msgs fields, shared by the bag reader/writer and the ROS node.

There is no cv_bridge wheel (../shared/ROS2_ON_PIP.md), so this is the conversion. It works
on plain fields, so rosbags and rclpy messages go through the same code; decoded images are
in OpenCV layout (grey (H, W) or BGR (H, W, 3)) whatever the message's channel order.
"""
from __future__ import annotations

import numpy as np

from .camera import Camera, CameraError

#: encoding -> (channels, bytes per channel)
ENCODINGS = {
    "mono8": (1, 1),
    "mono16": (1, 2),
    "bgr8": (3, 1),
    "rgb8": (3, 1),
    "bgra8": (4, 1),
    "rgba8": (4, 1),
}

#: Channel order that turns each colour encoding into BGR.
_TO_BGR = {"bgr8": [0, 1, 2], "rgb8": [2, 1, 0], "bgra8": [0, 1, 2], "rgba8": [2, 1, 0]}

#: CameraInfo distortion models whose coefficients mean what OpenCV's do.
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")


def decode_image(encoding: str, height: int, width: int, step: int, data,
                 is_bigendian: bool = False) -> np.ndarray:
    """Image message fields -> a new array: uint8 grey, uint16 grey (mono16) or uint8 BGR.

    Raises ValueError naming the problem for an unsupported encoding, a non-positive size,
    a row step shorter than a row, or data that is empty or not ``step * height`` bytes.
    """
    if encoding not in ENCODINGS:
        raise ValueError(f"unsupported image encoding {encoding!r}; supported: {', '.join(ENCODINGS)}")
    if height <= 0 or width <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    channels, depth = ENCODINGS[encoding]
    row_bytes = width * channels * depth
    if step < row_bytes:
        raise ValueError(f"step {step} is shorter than one row of {width} {encoding} pixels "
                         f"({row_bytes} bytes)")
    buffer = np.frombuffer(memoryview(data).cast("B"), dtype=np.uint8)
    if buffer.size == 0:
        raise ValueError("image data is empty")
    if buffer.size != step * height:
        raise ValueError(f"image data has {buffer.size} bytes, step {step} x height {height} = "
                         f"{step * height} expected")
    rows = buffer.reshape(height, step)[:, :row_bytes]
    if depth == 2:
        grey = rows.copy().view(">u2" if is_bigendian else "<u2").reshape(height, width)
        return grey.astype(np.uint16)
    pixels = rows.reshape(height, width, channels)
    if channels == 1:
        return pixels[..., 0].copy()
    return np.ascontiguousarray(pixels[..., _TO_BGR[encoding]])


def encode_image(image: np.ndarray) -> tuple[str, int, bytes]:
    """(encoding, step, data) of a grey uint8/uint16 or BGR/BGRA uint8 image (little-endian)."""
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim == 2 and image.dtype == np.uint8:
        encoding = "mono8"
    elif image.ndim == 2 and image.dtype == np.uint16:
        encoding = "mono16"
    elif image.ndim == 3 and image.dtype == np.uint8 and image.shape[2] in (3, 4):
        encoding = "bgr8" if image.shape[2] == 3 else "bgra8"
    else:
        raise ValueError(f"cannot encode a {image.dtype} image of shape {image.shape}: "
                         "expected uint8 or uint16 grey, or uint8 BGR / BGRA")
    if image.size == 0:
        raise ValueError(f"cannot encode an empty image of shape {image.shape}")
    data = np.ascontiguousarray(image, dtype=image.dtype.newbyteorder("<")).tobytes()
    return encoding, len(data) // image.shape[0], data


def camera_from_info(info) -> Camera:
    """Camera of a sensor_msgs/CameraInfo (any object with its fields: rosbags or rclpy).

    Raises CameraError for a distortion model OpenCV cannot apply as given or for
    impossible intrinsics.
    """
    k = np.asarray(info.k, dtype=float).reshape(3, 3)
    d = tuple(float(x) for x in info.d)
    if not any(d):
        d = ()
    elif info.distortion_model not in DISTORTION_MODELS:
        raise CameraError(f"unsupported distortion model {info.distortion_model!r}; "
                          f"supported: {', '.join(DISTORTION_MODELS)}")
    return Camera(k[0, 0], k[1, 1], k[0, 2], k[1, 2], int(info.width), int(info.height), d)

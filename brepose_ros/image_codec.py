"""Pixels in and out: sensor_msgs fields, compressed images and image files <-> numpy.

There is no cv_bridge wheel (../shared/ROS2_ON_PIP.md), so this is the conversion. It works
on plain fields, so rosbags and rclpy messages go through the same code; decoded images are
in OpenCV layout (grey (H, W) or BGR (H, W, 3)) whatever the message's channel order.

Every decoder checks the pixel count against ``max_pixels`` *before* it allocates: a raw
Image from its width and height fields, a PNG or JPEG from the size in its own header (a
400 KB PNG can claim 50,000 x 50,000 pixels), any other file format through OpenCV's own
cap, which this module sets to the same limit.
"""
from __future__ import annotations

import os
import struct
from pathlib import Path

#: default bound on decoded pixels: 4096 x 4096 holds a 4K camera (3840 x 2160) with room to
#: spare, and its BGR copy (50 MB) is far from hurting a robot's memory
MAX_IMAGE_PIXELS = 4096 * 4096
# OpenCV reads this once, at its first decode: set it before cv2 is imported anywhere
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(MAX_IMAGE_PIXELS))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from .camera import Camera, CameraError  # noqa: E402

#: a compressed image or image file larger than this is refused unread (a 4096 x 4096 PNG of
#: noise is 50 MB)
MAX_COMPRESSED_BYTES = 64 * 1024 * 1024

#: raw encoding -> (bytes per pixel, OpenCV conversion to BGR or grey, or None for plain)
_BAYER8 = {"bayer_rggb8": cv2.COLOR_BayerBG2BGR, "bayer_bggr8": cv2.COLOR_BayerRG2BGR,
           "bayer_gbrg8": cv2.COLOR_BayerGR2BGR, "bayer_grbg8": cv2.COLOR_BayerGB2BGR}
# (cv_bridge's table: OpenCV names a Bayer pattern by its second row, ROS by its first)
_BAYER16 = {"bayer_rggb16": cv2.COLOR_BayerBG2GRAY, "bayer_bggr16": cv2.COLOR_BayerRG2GRAY,
            "bayer_gbrg16": cv2.COLOR_BayerGR2GRAY, "bayer_grbg16": cv2.COLOR_BayerGB2GRAY}
_YUV422 = {"yuv422": cv2.COLOR_YUV2BGR_UYVY, "uyvy": cv2.COLOR_YUV2BGR_UYVY,
           "yuv422_yuy2": cv2.COLOR_YUV2BGR_YUYV, "yuyv": cv2.COLOR_YUV2BGR_YUYV}

#: encoding -> (channels, bytes per channel)
ENCODINGS = {
    "mono8": (1, 1),
    "mono16": (1, 2),
    "bgr8": (3, 1),
    "rgb8": (3, 1),
    "bgra8": (4, 1),
    "rgba8": (4, 1),
    **{name: (1, 1) for name in _BAYER8},
    **{name: (1, 2) for name in _BAYER16},
    **{name: (2, 1) for name in _YUV422},
}

#: Channel order that turns each colour encoding into BGR.
_TO_BGR = {"bgr8": [0, 1, 2], "rgb8": [2, 1, 0], "bgra8": [0, 1, 2], "rgba8": [2, 1, 0]}

#: CameraInfo distortion models whose coefficients mean what OpenCV's do.
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")

#: compressed formats by their file signature
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SIGNATURE = b"\xff\xd8"
#: JPEG start-of-frame markers (SOF0..SOF15 less DHT, JPG and DAC), which carry the size
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def check_pixels(width: int, height: int, max_pixels: int, what: str = "image") -> None:
    """ValueError unless ``width x height`` is a positive size of at most ``max_pixels``."""
    if height <= 0 or width <= 0:
        raise ValueError(f"{what} size must be positive, got {width}x{height}")
    if width * height > max_pixels:
        raise ValueError(f"{what} of {width}x{height} pixels exceeds the limit of {max_pixels} pixels")


def decode_image(encoding: str, height: int, width: int, step: int, data,
                 is_bigendian: bool = False, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """Image message fields -> a new array: uint8 grey, uint16 grey (mono16, 16-bit Bayer) or
    uint8 BGR (colour, 8-bit Bayer, YUV 4:2:2).

    Raises ValueError naming the problem for an unsupported encoding, a non-positive or too
    large size, a row step shorter than a row, an odd width for YUV 4:2:2, or data that is
    empty or not ``step * height`` bytes.
    """
    if encoding not in ENCODINGS:
        raise ValueError(f"unsupported image encoding {encoding!r}; supported: {', '.join(ENCODINGS)}")
    check_pixels(width, height, max_pixels)
    channels, depth = ENCODINGS[encoding]
    if encoding in _YUV422 and width % 2:
        raise ValueError(f"{encoding} images need an even width, got {width}")
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
        grey = rows.copy().view(">u2" if is_bigendian else "<u2").reshape(height, width).astype(np.uint16)
        return cv2.cvtColor(grey, _BAYER16[encoding]) if encoding in _BAYER16 else grey
    pixels = rows.reshape(height, width, channels)
    if encoding in _BAYER8:
        return cv2.cvtColor(np.ascontiguousarray(pixels[..., 0]), _BAYER8[encoding])
    if encoding in _YUV422:
        return cv2.cvtColor(np.ascontiguousarray(pixels), _YUV422[encoding])
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


def compressed_size(data: bytes) -> tuple[str, int, int]:
    """(``"png"`` or ``"jpeg"``, width, height) read from the header alone, nothing decoded.

    Raises ValueError for data that is neither, or whose header is cut short or damaged.
    """
    if data[:8] == _PNG_SIGNATURE:
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise ValueError("PNG data is cut short before its IHDR header")
        width, height = struct.unpack(">II", data[16:24])
        return "png", width, height
    if data[:2] == _JPEG_SIGNATURE:
        return ("jpeg", *_jpeg_size(data))
    raise ValueError(f"compressed image data is neither PNG nor JPEG (starts with {bytes(data[:8])!r})")


def _jpeg_size(data: bytes) -> tuple[int, int]:
    """Width and height of a JPEG from its start-of-frame segment."""
    at = 2
    while at + 4 <= len(data):
        if data[at] != 0xFF:
            raise ValueError(f"JPEG data is damaged (no marker at byte {at})")
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # markers without a length
            at += 2
            continue
        length = struct.unpack(">H", data[at + 2:at + 4])[0]
        if marker in _JPEG_SOF:
            if at + 9 > len(data):
                break
            height, width = struct.unpack(">HH", data[at + 5:at + 9])
            return width, height
        if marker == 0xDA or length < 2:  # scan data before any frame header: not a JPEG we read
            break
        at += 2 + length
    raise ValueError("JPEG data has no frame header (cut short or damaged)")


def decode_compressed(data, max_pixels: int = MAX_IMAGE_PIXELS, what: str = "compressed image") -> np.ndarray:
    """PNG or JPEG bytes -> uint8 grey, uint16 grey or uint8 BGR, the size checked first.

    Raises ValueError for other data, a header size over ``max_pixels`` or data that
    does not decode to the size its header states.
    """
    data = bytes(memoryview(data).cast("B"))
    if len(data) > MAX_COMPRESSED_BYTES:
        raise ValueError(f"{what} of {len(data)} bytes exceeds the limit of {MAX_COMPRESSED_BYTES} bytes")
    kind, width, height = compressed_size(data)
    check_pixels(width, height, max_pixels, f"{what} ({kind})")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None or image.shape[:2] != (height, width):
        raise ValueError(f"{what} ({kind}, {width}x{height} by its header) does not decode: "
                         "the data is cut short or damaged")
    return _usable(image)


def _usable(image: np.ndarray) -> np.ndarray:
    """A decoded image in the layouts the estimator takes: alpha dropped, 16-bit colour to 8."""
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.ndim == 3 and image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    return image


def encode_compressed(image: np.ndarray, kind: str = "png", jpeg_quality: int = 95) -> tuple[str, bytes]:
    """(CompressedImage format, data) of a grey or BGR image as ``png`` or ``jpeg``, formats
    written as image_transport's compressed plugin does (``"bgr8; png compressed bgr8"``)."""
    if kind not in ("png", "jpeg"):
        raise ValueError(f"compression must be 'png' or 'jpeg', got {kind!r}")
    encoding, _, _ = encode_image(image)
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if kind == "jpeg" else []
    ok, data = cv2.imencode(".png" if kind == "png" else ".jpg", image, params)
    if not ok:
        raise ValueError(f"cannot encode a {image.dtype} image of shape {image.shape} as {kind}")
    return f"{encoding}; {kind} compressed {encoding}", data.tobytes()


def read_image_file(path: str | Path, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """An image file as the estimator takes it, its size checked before decoding.

    PNG and JPEG sizes come from their headers; other formats OpenCV reads (BMP, TIFF,
    PPM, ...) are bounded by OpenCV's own cap, which this module sets to the default limit.
    Raises ValueError naming the file and the problem.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        if size > MAX_COMPRESSED_BYTES:
            raise ValueError(f"image {path} of {size} bytes exceeds the limit of {MAX_COMPRESSED_BYTES} bytes")
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read image {path}: {exc.strerror}") from None
    if data[:8] == _PNG_SIGNATURE or data[:2] == _JPEG_SIGNATURE:
        try:
            return decode_compressed(data, max_pixels, "image")
        except ValueError as exc:
            raise ValueError(f"image {path}: {exc}") from None
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
    if image is None:
        raise ValueError(f"cannot read image {path}: not an image file OpenCV can decode, or over "
                         f"{os.environ['OPENCV_IO_MAX_IMAGE_PIXELS']} pixels")
    check_pixels(image.shape[1], image.shape[0], max_pixels, f"image {path}")
    return _usable(image)


def camera_from_info(info, rectified: bool = False) -> Camera:
    """Camera of a sensor_msgs/CameraInfo (any object with its fields: rosbags or rclpy).

    Raw images (``rectified`` False) use K and the distortion D; rectified images (an
    image_proc ``image_rect`` topic) the projection P and no distortion, as image_geometry
    does. Raises CameraError for a distortion model OpenCV cannot apply as given, arrays
    of the wrong length, or impossible intrinsics.
    """
    if len(info.k) != 9 or len(info.p) not in (0, 12):
        raise CameraError(f"CameraInfo K must have 9 and P 12 elements, got {len(info.k)} and {len(info.p)}")
    if rectified:
        p = np.asarray(info.p, dtype=float).reshape(3, 4) if len(info.p) else np.zeros((3, 4))
        if not p[0, 0]:
            raise CameraError("input_is_rectified is set but the CameraInfo's P is all zero "
                              "(an uncalibrated camera)")
        return Camera(p[0, 0], p[1, 1], p[0, 2], p[1, 2], int(info.width), int(info.height))
    k = np.asarray(info.k, dtype=float).reshape(3, 3)
    d = tuple(float(x) for x in info.d)
    if not any(d):
        d = ()
    elif info.distortion_model not in DISTORTION_MODELS:
        raise CameraError(f"unsupported distortion model {info.distortion_model!r}; "
                          f"supported: {', '.join(DISTORTION_MODELS)}")
    if not all(np.isfinite(d)):
        raise CameraError(f"distortion coefficients must be finite, got {list(d)}")
    return Camera(k[0, 0], k[1, 1], k[0, 2], k[1, 2], int(info.width), int(info.height), d)

"""Pixel formats: Bayer and YUV 4:2:2 decode to the right colours, PNG and JPEG sizes are read
from their headers, and CameraInfo gives K + D for raw images, P for rectified ones."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from brepose_ros.camera import Camera, CameraError
from brepose_ros.image_codec import (compressed_size, decode_compressed, decode_image, encode_compressed,
                                     read_image_file, camera_from_info)
from brepose_ros.ros.messages import camera_info_msg
from std_msgs.msg import Header

pytestmark = pytest.mark.ros  # CameraInfo messages

BGR = (10, 100, 200)  # a colour whose channels differ, so a swapped pattern shows
#: the colour filter at (row 0, col 0), (0, 1), (1, 0), (1, 1) of each ROS Bayer pattern
PATTERNS = {"bayer_rggb8": "RGGB", "bayer_bggr8": "BGGR", "bayer_gbrg8": "GBRG", "bayer_grbg8": "GRBG"}


def mosaic(pattern: str, height: int = 16, width: int = 20) -> np.ndarray:
    """A uniform BGR colour seen through a Bayer filter of the given pattern."""
    value = dict(zip("BGR", BGR))
    raw = np.zeros((height, width), np.uint8)
    for (dy, dx), colour in zip([(0, 0), (0, 1), (1, 0), (1, 1)], pattern):
        raw[dy::2, dx::2] = value[colour]
    return raw


@pytest.mark.parametrize("encoding", PATTERNS)
def test_bayer_patterns_decode_to_their_colour(encoding):
    raw = mosaic(PATTERNS[encoding])
    image = decode_image(encoding, *raw.shape, raw.shape[1], raw.tobytes())
    assert image.shape == raw.shape + (3,) and image.dtype == np.uint8
    np.testing.assert_array_equal(image[4:-4, 4:-4].reshape(-1, 3), np.tile(BGR, ((raw.shape[0] - 8) * 12, 1)))


def test_bayer16_decodes_to_grey_uint16():
    raw = (mosaic("RGGB").astype(np.uint16) * 256)
    image = decode_image("bayer_rggb16", *raw.shape, raw.shape[1] * 2, raw.tobytes())
    assert image.dtype == np.uint16 and image.ndim == 2
    grey = 0.299 * BGR[2] + 0.587 * BGR[1] + 0.114 * BGR[0]
    assert abs(float(image[8, 10]) / 256 - grey) < 2


#: OpenCV's encoders of the two 4:2:2 byte orders, to make the test data
TO_YUV422 = {"UYVY": cv2.COLOR_BGR2YUV_UYVY, "YUYV": cv2.COLOR_BGR2YUV_YUY2}


@pytest.mark.parametrize("encoding, order", [("yuv422", "UYVY"), ("uyvy", "UYVY"), ("yuv422_yuy2", "YUYV"),
                                             ("yuyv", "YUYV")])
def test_yuv422_decodes_to_its_colour(encoding, order):
    data = cv2.cvtColor(np.full((4, 8, 3), BGR, np.uint8), TO_YUV422[order])
    image = decode_image(encoding, 4, 8, 16, data.tobytes())
    assert image.shape == (4, 8, 3)
    assert np.abs(image.astype(int) - BGR).max() <= 2, "the other byte order gives other colours"


@pytest.mark.parametrize("kind", ["png", "jpeg"])
def test_compressed_round_trip_and_header_size(kind):
    image = np.zeros((48, 64, 3), np.uint8)
    image[10:30, 20:50] = BGR
    fmt, data = encode_compressed(image, kind)
    assert fmt == f"bgr8; {kind} compressed bgr8"
    assert compressed_size(data) == (kind, 64, 48)
    decoded = decode_compressed(data)
    assert decoded.shape == image.shape
    assert np.abs(decoded.astype(int) - image).mean() <= (0 if kind == "png" else 3)


def test_compressed_size_is_checked_before_decoding():
    _, data = encode_compressed(np.zeros((48, 64), np.uint8), "png")
    with pytest.raises(ValueError, match="64x48 pixels exceeds the limit of 1000 pixels"):
        decode_compressed(data, max_pixels=1000)
    assert decode_compressed(data, max_pixels=64 * 48).shape == (48, 64)


def test_16_bit_png_stays_16_bit_and_alpha_is_dropped(tmp_path):
    grey16 = np.arange(48 * 64, dtype=np.uint16).reshape(48, 64) * 20
    bgra = np.dstack([np.full((48, 64), c, np.uint8) for c in (*BGR, 255)])
    cv2.imwrite(str(tmp_path / "grey16.png"), grey16)
    cv2.imwrite(str(tmp_path / "bgra.png"), bgra)
    np.testing.assert_array_equal(read_image_file(tmp_path / "grey16.png"), grey16)
    assert read_image_file(tmp_path / "bgra.png").shape == (48, 64, 3)


def test_other_file_formats_are_read_and_bounded(tmp_path):
    cv2.imwrite(str(tmp_path / "part.bmp"), np.full((48, 64), 7, np.uint8))
    assert read_image_file(tmp_path / "part.bmp").shape == (48, 64)
    with pytest.raises(ValueError, match="exceeds the limit of 100 pixels"):
        read_image_file(tmp_path / "part.bmp", max_pixels=100)


def test_camera_info_raw_uses_k_and_d_rectified_uses_p():
    camera = Camera(300.0, 310.0, 80.5, 59.0, 160, 120, (0.1, -0.05, 0.001, 0.002, 0.01))
    info = camera_info_msg(camera, Header())
    assert camera_from_info(info) == camera
    info.p = [290.0, 0.0, 81.0, 0.0, 0.0, 295.0, 60.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    assert camera_from_info(info, rectified=True) == Camera(290.0, 295.0, 81.0, 60.0, 160, 120)
    info.p = [0.0] * 12
    with pytest.raises(CameraError, match="P is all zero"):
        camera_from_info(info, rectified=True)


@pytest.mark.parametrize("encoding, order", [("bgr8", [0, 1, 2]), ("rgb8", [2, 1, 0]), ("bgra8", [0, 1, 2, 3]),
                                             ("rgba8", [2, 1, 0, 3])])
def test_colour_encodings_decode_to_the_same_bgr_image(encoding, order):
    """A colour photo arrives as rgb8 as often as bgr8 (issue 13): every 8-bit colour order
    decodes to the same BGR pixels, alpha dropped."""
    bgr = np.random.default_rng(0).integers(0, 256, (6, 5, 3), dtype=np.uint8)
    pixels = np.concatenate([bgr, np.full((6, 5, 1), 77, np.uint8)], axis=2)[..., order]
    image = decode_image(encoding, 6, 5, 5 * len(order), np.ascontiguousarray(pixels).tobytes())
    np.testing.assert_array_equal(image, bgr)

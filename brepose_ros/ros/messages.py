"""ROS message helpers shared by the node and the replay tools.

Conversions (Image, CameraInfo, PoseStamped, DiagnosticStatus <-> numpy and the package's
types) live here so that no script re-implements them; the pixel formats themselves are
``image_codec``'s business. ``make_executor`` builds the node's executor.
"""
from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from ..camera import Camera
from ..geometry import matrix_from_quaternion, quaternion_from_matrix
from ..image_codec import MAX_IMAGE_PIXELS, decode_compressed, decode_image, encode_compressed, encode_image


def latest_only(reliability: ReliabilityPolicy) -> QoSProfile:
    """Depth 1, keep last: the DDS reader itself keeps only the newest frame, never a backlog."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=reliability)


#: what cameras publish with (best effort); our players also offer reliable
SENSOR_QOS = qos_profile_sensor_data
RELIABLE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5, reliability=ReliabilityPolicy.RELIABLE)
PUBLISHER_QOS = {"best_effort": SENSOR_QOS, "reliable": RELIABLE_QOS}
DIAGNOSTICS_TOPIC = "/diagnostics"
#: image_transport's name for the compressed images of a base topic
COMPRESSED_SUFFIX = "/compressed"


def stamp_ns(stamp: Time) -> int:
    """A header stamp as one integer: the key that ties a pose and diagnostics to their image."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def stamp_from_ns(ns: int) -> Time:
    return Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def image_from_msg(msg: Image | CompressedImage, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """Pixels of an Image or CompressedImage (PNG or JPEG) message, at most ``max_pixels``
    of them; ValueError (from image_codec) names what is wrong."""
    if isinstance(msg, CompressedImage):
        if "compresseddepth" in msg.format.lower():
            raise ValueError(f"CompressedImage format {msg.format!r} (depth images) is not supported")
        return decode_compressed(msg.data, max_pixels)
    return decode_image(msg.encoding, msg.height, msg.width, msg.step, msg.data, bool(msg.is_bigendian),
                        max_pixels)


def compressed_image_msg(image: np.ndarray, header: Header, kind: str = "png") -> CompressedImage:
    fmt, data = encode_compressed(image, kind)
    return CompressedImage(header=header, format=fmt, data=data)


def image_msg(image: np.ndarray, header: Header) -> Image:
    encoding, step, data = encode_image(image)
    return Image(header=header, height=image.shape[0], width=image.shape[1],
                 encoding=encoding, is_bigendian=0, step=step, data=data)


def camera_info_msg(camera: Camera, header: Header) -> CameraInfo:
    msg = CameraInfo(header=header, width=camera.width, height=camera.height)
    msg.distortion_model = "plumb_bob"
    msg.d = [float(d) for d in camera.dist_coeffs]
    msg.k = [float(v) for v in camera.K.ravel()]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    msg.p = [camera.fx, 0.0, camera.cx, 0.0, 0.0, camera.fy, camera.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return msg


def pose_msg(R: np.ndarray, t: np.ndarray, header: Header) -> PoseStamped:
    """T_cam_model as a PoseStamped in the image's frame (CONVENTIONS.md: position = t)."""
    msg = PoseStamped(header=header)
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in t)
    q = quaternion_from_matrix(R)
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    return msg


def pose_with_covariance_msg(R: np.ndarray, t: np.ndarray, covariance: np.ndarray | None,
                             header: Header) -> PoseWithCovarianceStamped:
    """The pose with its 6x6 covariance (x, y, z, then rotations about x, y, z: REP 103 order);
    an unknown covariance is written as all -1, which no real covariance can be."""
    msg = PoseWithCovarianceStamped(header=header)
    msg.pose.pose = pose_msg(R, t, header).pose
    msg.pose.covariance = (np.full(36, -1.0) if covariance is None
                           else np.asarray(covariance, dtype=float).reshape(36)).tolist()
    return msg


def pose_from_msg(msg: PoseStamped) -> tuple[np.ndarray, np.ndarray]:
    p, o = msg.pose.position, msg.pose.orientation
    return matrix_from_quaternion(np.array([o.x, o.y, o.z, o.w])), np.array([p.x, p.y, p.z])


def diagnostic_status(name: str, level: bytes, message: str, hardware_id: str, values: dict) -> DiagnosticStatus:
    """A DiagnosticStatus; numbers are written with 6 significant digits."""
    def text(v) -> str:
        return f"{v:.6g}" if isinstance(v, float) else str(v)
    return DiagnosticStatus(level=level, name=name, message=message, hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=text(v)) for k, v in values.items()])


def status_values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


class _StartedPool(ThreadPoolExecutor):
    """A thread pool whose ``submit`` returns once the task has started running."""

    def submit(self, fn, /, *args, **kwargs):
        started = threading.Event()

        def run():
            started.set()
            return fn(*args, **kwargs)

        future = super().submit(run)
        started.wait()
        return future


def make_executor(threads: int, context: Context | None = None) -> MultiThreadedExecutor:
    """A MultiThreadedExecutor that does not spin while a callback waits for a pool thread.

    rclpy 9.1 (the kilted wheels) yields a submitted task again as long as no pool thread has
    started it, without blocking in between (ros2/rclpy#1452, fixed upstream by #1547): the
    spinning thread then holds the GIL and starves the pool and the estimator. Handing tasks
    to a pool whose ``submit`` waits for the start closes that window (bench/node_latency.py
    measures both).
    """
    executor = MultiThreadedExecutor(num_threads=threads, context=context)
    executor._executor.shutdown(wait=False)
    executor._executor = _StartedPool(threads)
    return executor

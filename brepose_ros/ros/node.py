"""The rclpy adapter: images in, poses + diagnostics + a debug overlay out (docs/ros.md).

Topics (node name ``estimator``; relative names can be remapped with ``--ros-args -r``):

- in  ``image_raw`` (sensor_msgs/Image; mono8, mono16, bgr8, rgb8, bgra8, rgba8, the 8- and
  16-bit Bayer patterns, yuv422/uyvy and yuv422_yuy2/yuyv) or, with ``image_transport`` =
  ``compressed``, ``image_raw/compressed`` (sensor_msgs/CompressedImage, PNG or JPEG), and
  ``camera_info`` (sensor_msgs/CameraInfo). Both are depth 1, keep last; their reliability
  follows the publishers (:class:`InputSubscription`) unless a parameter file sets
  ``qos_overrides./image_raw.subscription.reliability`` (rclpy's QoSOverridingOptions);
- out ``~/pose`` (geometry_msgs/PoseStamped) and ``~/pose_with_covariance``
  (geometry_msgs/PoseWithCovarianceStamped), only when the part is found, and
  ``~/debug_image`` (sensor_msgs/Image bgr8, only while someone subscribes); with more than
  one part these become ``~/<part>/pose`` etc.;
- out ``/diagnostics`` (diagnostic_msgs/DiagnosticArray): one array per image, header copied
  from the image, one status named ``estimator: <part>`` per part. Levels: OK = found with
  error ratio <= ``pose.warn_error_ratio``; WARN = not found (score below
  ``pose.min_score``, confidence below ``pose.min_confidence``, or the pose outside
  ``pose.min_distance`` - ``pose.max_distance``), error ratio above it, or a
  pose the image cannot tell from its symmetric twin (``Estimate.ambiguous``); ERROR = the
  image or the intrinsics could not be used, or the estimator raised (also logged). Values:
  found, score, confidence (the probability that the pose is right), error_ratio,
  view_index, image_edges, matched_pairs, nearest_pairs, symmetry_margin (-1 for a part
  without near symmetry), twin_tie, skipped (the steps ``search.time_budget_ms`` left out,
  empty without one), shading_fit (how much of the grey level over the part's silhouette its surface
  explains at the pose, weighed by the confidence; -1 for a graph without the surface),
  estimator_ms, latency_ms (receipt
  to answer), frames_skipped (frames received but replaced by a newer one before the worker
  got to them), frames_lost (samples the DDS reader reported lost), input_hz, and the
  estimator's own stage timings as ``<stage>_ms``. Besides, a status ``estimator: input``
  once a second while no image arrives (WARN, with the publishers seen) or while frames are
  being lost (WARN, with the count and the remedy).

Threads: the subscription callbacks (their own callback group) only store the newest frame;
one worker thread decodes it, finds its edges once for all parts (``Estimator.detect``) and
hands both to every part at once, each part's estimator on its own thread, so several parts
cost about the time of the slowest one on enough cores and a slow image never builds a
backlog. Each part publishes its pose as soon as it has it;
the diagnostics array follows when every part has answered. Each estimator spreads one
image's work over its own ``matching.workers`` threads (default 0 = one per core). The executor
threads (``executor_threads``) keep the input callbacks, timers and parameter services
responsive meanwhile; ``messages.make_executor`` builds the executor with a work-around for
a busy loop of rclpy 9.1's MultiThreadedExecutor.

Parameters: :data:`NODE_PARAMETERS` and every estimator parameter under its
``params.EstimatorParams.flat()`` name (``matching.empty_coefficient``...), each with its
range in the descriptor. Every value is checked at start (a bad one stops the start with the
reason) and at run time (a bad change is refused with the reason). Estimator parameters,
the intrinsics and ``input_is_rectified`` can change at run time; the worker hands new
estimator parameters over between two images, never during one.
"""
from __future__ import annotations

import argparse
import collections
import copy
import re
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import rclpy
import yaml
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from .. import __version__
from ..aspect_graph import SUFFIX as GRAPH_SUFFIX
from ..aspect_graph import AspectGraph
from ..camera import Camera, CameraError
from ..evaluation.overlay import draw_overlay
from ..image_codec import MAX_IMAGE_PIXELS, camera_from_info
from ..online.confidence import load_calibration
from ..online.estimator import Estimate, Estimator, not_found_reason
from ..online.workers import WorkerPool
from ..params import EstimatorParams, field_docs, field_ranges, one_line
from .messages import (COMPRESSED_SUFFIX, DIAGNOSTICS_TOPIC, diagnostic_status, image_from_msg,
                       image_msg, latest_only, make_executor, pose_msg, pose_with_covariance_msg)

NODE_NAME = "estimator"
INTRINSICS = ("fx", "fy", "cx", "cy")
TRANSPORTS = ("raw", "compressed")
#: seconds an image waits for the first CameraInfo when there are no fallback intrinsics
CAMERA_INFO_GRACE = 0.2
#: the input status is published this often while no image arrives or frames are lost, s
HEARTBEAT_PERIOD = 1.0
#: how often the input subscriptions compare their reliability with their publishers', s: a
#: publisher that appears is followed within this time
QOS_CHECK_PERIOD = 0.25
#: input_hz counts the frames received in this window, s
RATE_WINDOW = 2.0
#: an ERROR log line per cause at most this often, s: a camera sending bad frames at 30 Hz
#: must not flood the log (diagnostics still carry every one)
LOG_THROTTLE = 5.0
#: largest focal length or principal point accepted as fallback intrinsics, pixels
MAX_INTRINSIC = 1e6


@dataclass(frozen=True)
class NodeParameter:
    default: Any
    description: str
    read_only: bool = False
    range: tuple[float, float] | None = None


#: the node's own parameters; graphs, part names, threads and the transport cannot change
#: while running
NODE_PARAMETERS: dict[str, NodeParameter] = {
    "graphs": NodeParameter(Parameter.Type.STRING_ARRAY, "paths of precompiled aspect graphs (brepose-compile), "
                            "one per part", True),
    "part_names": NodeParameter(Parameter.Type.STRING_ARRAY, "name of each graph's part, used in topics and "
                                "diagnostics; empty: the graph file names without .brepose.npz", True),
    **{name: NodeParameter(0.0, f"fallback {what}, pixels, used until a CameraInfo arrives; 0 = no fallback",
                           range=(0.0, MAX_INTRINSIC))
       for name, what in zip(INTRINSICS, ("focal length x", "focal length y", "principal point x",
                                          "principal point y"))},
    "executor_threads": NodeParameter(2, "threads of the MultiThreadedExecutor started by main()", True, (1, 16)),
    "debug_image": NodeParameter(True, "publish the overlay image while ~/debug_image has subscribers"),
    "image_transport": NodeParameter("raw", "'raw': sensor_msgs/Image on image_raw; 'compressed': "
                                     "sensor_msgs/CompressedImage (PNG, JPEG) on image_raw/compressed", True),
    "input_is_rectified": NodeParameter(False, "the images are rectified (image_proc's image_rect): use the "
                                        "CameraInfo's P and no distortion instead of K and D"),
    "max_image_pixels": NodeParameter(MAX_IMAGE_PIXELS, "images with more pixels are refused before decoding",
                                      range=(1, 1 << 28)),
}


class StartupError(ValueError):
    """The node cannot start: a graph file is missing or refused, or a parameter is wrong."""


class BadInput(ValueError):
    """An image or its intrinsics cannot be used; the node answers with an ERROR and goes on."""


class NewestFrame:
    """One-slot mailbox between the image callback and the worker: a new frame replaces a
    waiting one, so the worker always works on the latest image and never on a backlog."""

    def __init__(self):
        self._cond = threading.Condition()
        self._item = None
        self._closed = False
        self.replaced = 0

    def put(self, item) -> None:
        with self._cond:
            if self._item is not None:
                self.replaced += 1
            self._item = item
            self._cond.notify()

    def take(self):
        """The newest item, waiting for one; None once closed."""
        with self._cond:
            self._cond.wait_for(lambda: self._item is not None or self._closed)
            item, self._item = self._item, None
            return None if self._closed else item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class InputSubscription:
    """A depth-1 input subscription whose reliability follows its publishers.

    The profile is rclpy's QoSOverridingOptions default, so a parameter file can set every
    policy (``qos_overrides./image_raw.subscription.reliability: reliable``...). Left at
    ``best_available`` the subscription is re-created as the publishers require, as
    rosbag2's recorder does: reliable while every publisher is reliable (large frames then
    survive the trip between processes, docs/ros.md), best effort as soon as one publisher is
    best effort (a reliable reader does not match it), best effort before any publisher is
    seen. The new subscription is created before the old one is destroyed, so no frame falls
    in between. ``lost`` counts the samples the DDS reader reported lost.
    """

    def __init__(self, node: Node, msg_type, topic: str, callback: Callable, group=None):
        self.node, self.msg_type, self.topic, self.callback = node, msg_type, topic, callback
        self.group = group
        self.lost = 0
        self._lock = threading.Lock()
        profile = latest_only(ReliabilityPolicy.BEST_AVAILABLE)
        # the first subscription declares the qos_overrides parameters and applies them to
        # ``profile``; it is replaced at once when they leave reliability to the publishers
        self.subscription = self._create(profile, QoSOverridingOptions.with_default_policies())
        self.profile = profile
        self.follows_publishers = profile.reliability == ReliabilityPolicy.BEST_AVAILABLE
        self.reliability = profile.reliability
        if self.follows_publishers:
            self.update()

    def _create(self, profile: QoSProfile, overriding: QoSOverridingOptions | None = None):
        events = SubscriptionEventCallbacks(message_lost=self._on_lost)
        return self.node.create_subscription(self.msg_type, self.topic, self.callback, profile,
                                             qos_overriding_options=overriding, event_callbacks=events,
                                             callback_group=self.group)

    def _on_lost(self, info) -> None:
        self.lost += info.total_count_change

    def wanted(self) -> ReliabilityPolicy:
        offered = [p.qos_profile.reliability for p in self.node.get_publishers_info_by_topic(self.topic)]
        if offered and all(r == ReliabilityPolicy.RELIABLE for r in offered):
            return ReliabilityPolicy.RELIABLE
        return ReliabilityPolicy.BEST_EFFORT

    def update(self) -> None:
        """Re-create the subscription if the publishers now want another reliability."""
        if not self.follows_publishers:
            return
        with self._lock:
            wanted = self.wanted()
            if wanted == self.reliability:
                return
            profile = copy.copy(self.profile)  # every overridden policy but the reliability stays
            profile.reliability = wanted
            old, self.subscription = self.subscription, self._create(profile)
            self.node.destroy_subscription(old)
            first, self.reliability = self.reliability == ReliabilityPolicy.BEST_AVAILABLE, wanted
        if not first:
            self.node.get_logger().info(f"{self.topic}: subscription now {wanted.name.lower()}, "
                                        "as its publishers offer")

    @property
    def reliability_name(self) -> str:
        return self.reliability.name.lower()


class FrameRate:
    """Frames received per second over the last ``RATE_WINDOW`` seconds."""

    def __init__(self):
        self._lock = threading.Lock()
        self._arrivals: collections.deque[float] = collections.deque()
        self.last = None

    def add(self, now: float) -> None:
        with self._lock:
            self._arrivals.append(now)
            self.last = now
            while now - self._arrivals[0] > RATE_WINDOW:
                self._arrivals.popleft()

    def hz(self, now: float) -> float:
        with self._lock:
            return sum(now - t <= RATE_WINDOW for t in self._arrivals) / RATE_WINDOW


@dataclass
class Part:
    """One part the node looks for: its estimator and its output topics."""

    name: str
    status_name: str
    estimator: Any
    pose_pub: Any
    pose_covariance_pub: Any
    debug_pub: Any


def diagnose(estimate: Estimate, params: EstimatorParams) -> tuple[bytes, str]:
    """Diagnostic level and message of one estimate (documented thresholds, module docstring)."""
    if not estimate.found:
        return DiagnosticStatus.WARN, f"part not found ({not_found_reason(estimate, params.pose)})"
    if estimate.error_ratio > params.pose.warn_error_ratio:
        return DiagnosticStatus.WARN, (f"found, but error ratio {estimate.error_ratio:.2f} > "
                                       f"pose.warn_error_ratio {params.pose.warn_error_ratio:g}")
    if estimate.ambiguous:
        return DiagnosticStatus.WARN, (f"found, but the image cannot tell the pose from its symmetric twin "
                                       f"(margin {estimate.symmetry_margin:.2f} < pose.twin_margin "
                                       f"{params.pose.twin_margin:g})")
    return DiagnosticStatus.OK, (f"found (score {estimate.score:.2f}, confidence {estimate.confidence:.2f}, "
                                 f"error ratio {estimate.error_ratio:.2f})")


def estimate_values(estimate: Estimate) -> dict[str, Any]:
    values = {"found": estimate.found, "score": float(estimate.score), "confidence": float(estimate.confidence),
              "error_ratio": float(estimate.error_ratio), "view_index": estimate.view_index,
              "image_edges": estimate.n_image_segments, "matched_pairs": estimate.n_matched,
              "nearest_pairs": estimate.n_nearest,
              # evidence over the symmetric twins; -1: the part has no near symmetry
              "symmetry_margin": -1.0 if estimate.symmetry_margin is None else float(estimate.symmetry_margin),
              # a twin the image does not tell from the pose scores as well: a coin toss
              "twin_tie": estimate.twin_tie,
              # the steps search.time_budget_ms left out on this image, space-separated
              "skipped": " ".join(estimate.skipped),
              # how much of the grey level over the silhouette the part's surface explains; -1: not computed
              "shading_fit": -1.0 if estimate.shading_fit is None else float(estimate.shading_fit)}
    values.update({f"{stage}_ms": 1000.0 * float(s) for stage, s in estimate.timings.items()})
    return values


def parameter_descriptor(description: str, read_only: bool, value_range) -> ParameterDescriptor:
    descriptor = ParameterDescriptor(description=description, read_only=read_only)
    if value_range is not None:
        low, high = value_range
        if isinstance(low, int) and isinstance(high, int):
            descriptor.integer_range = [IntegerRange(from_value=low, to_value=high, step=1)]
        else:
            descriptor.floating_point_range = [FloatingPointRange(from_value=float(low), to_value=float(high),
                                                                  step=0.0)]
    return descriptor


class EstimatorNode(Node):
    """Loads the parts' aspect graphs once, then answers every image (see module docstring).

    ``estimator_factory(graph, params)`` and ``graph_loader(path)`` are injectable so tests
    can run the ROS side without the vision pipeline; construction raises
    :class:`StartupError` with a message naming the file or parameter at fault.
    """

    def __init__(self, *, estimator_factory: Callable = Estimator,
                 graph_loader: Callable = AspectGraph.load, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        try:
            self._declare_parameters()
            self.params = self._estimator_params()
            transport = self.get_parameter("image_transport").value
            if transport not in TRANSPORTS:
                raise StartupError(f"image_transport must be one of {', '.join(TRANSPORTS)}, got {transport!r}")
            self.parts = self._load_parts(estimator_factory, graph_loader)
        except StartupError:
            self.destroy_node()
            raise
        self.camera_info: CameraInfo | None = None
        self._camera_info_arrived = threading.Event()
        self.frames = NewestFrame()
        self.rate = FrameRate()
        self._logged: dict[str, float] = {}
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        # the input callbacks only store; their own group keeps them from waiting behind a
        # timer or a parameter service on the executor
        inputs = MutuallyExclusiveCallbackGroup()
        self.camera_info_input = InputSubscription(self, CameraInfo, self.resolve_topic_name("camera_info"),
                                                   self._on_camera_info, inputs)
        image_topic = self.resolve_topic_name("image_raw")
        if transport == "compressed":
            self.image_input = InputSubscription(self, CompressedImage, image_topic + COMPRESSED_SUFFIX,
                                                 self._on_image, inputs)
        else:
            self.image_input = InputSubscription(self, Image, image_topic, self._on_image, inputs)
        #: one thread per part (the worker itself and len(parts) - 1 more)
        self._part_threads = WorkerPool(len(self.parts))
        self._lost_reported = 0
        self._started = time.perf_counter()
        self.create_timer(QOS_CHECK_PERIOD, self._follow_publishers)
        self.create_timer(HEARTBEAT_PERIOD, self._heartbeat)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._worker = threading.Thread(target=self._work, name="estimator-worker", daemon=True)
        self._worker.start()

    # -- start-up ---------------------------------------------------------------------------

    def _declare_parameters(self) -> None:
        docs, ranges = field_docs(), field_ranges()
        declarations = [(name, p.default, p.description, p.read_only, p.range)
                        for name, p in NODE_PARAMETERS.items()]
        declarations += [(name, value, docs[name], False, ranges.get(name))
                         for name, value in EstimatorParams().flat().items()]
        for name, default, description, read_only, value_range in declarations:
            try:
                self.declare_parameter(name, default, parameter_descriptor(description, read_only, value_range))
            except Exception as exc:  # rclpy raises several types for a bad override value
                raise StartupError(f"parameter {name}: {one_line(exc)}") from None

    def _estimator_params(self) -> EstimatorParams:
        names = EstimatorParams().flat()
        try:
            params = EstimatorParams().with_flat({n: self.get_parameter(n).value for n in names})
            load_calibration(params.pose.confidence_file)
            return params
        except ValueError as exc:
            raise StartupError(f"estimator parameters: {exc}") from None

    def _string_list(self, name: str) -> list[str]:
        """A string-array parameter; an unset one (no default exists) is an empty list."""
        try:
            return [s for s in self.get_parameter(name).value if s]
        except rclpy.exceptions.ParameterUninitializedException:
            return []

    def _load_parts(self, estimator_factory: Callable, graph_loader: Callable) -> list[Part]:
        paths = self._string_list("graphs")
        if not paths:
            raise StartupError("parameter 'graphs' is empty: give the precompiled aspect graph file(s) "
                               "to load (brepose-compile writes them; the node never compiles)")
        names = self._string_list("part_names") or [Path(p).name.removesuffix(GRAPH_SUFFIX) for p in paths]
        if len(names) != len(paths):
            raise StartupError(f"{len(paths)} graphs but {len(names)} part_names: give one name per graph")
        for name in names:
            if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", name):
                raise StartupError(f"part name {name!r} must start with a letter and contain only letters, "
                                   "digits and '_' (it becomes a topic name)")
        if len(set(names)) != len(names):
            raise StartupError(f"part names must be unique, got {names}")
        graphs = []
        for name, path in zip(names, paths):
            try:
                graphs.append(graph_loader(path))
            except (ValueError, OSError) as exc:
                raise StartupError(f"aspect graph of part {name!r} refused: {exc}") from None
        parts = []
        for name, graph in zip(names, graphs):
            prefix = "~" if len(graphs) == 1 else f"~/{name}"
            parts.append(Part(name, f"{self.get_name()}: {name}", estimator_factory(graph, self.params),
                              self.create_publisher(PoseStamped, f"{prefix}/pose", 10),
                              self.create_publisher(PoseWithCovarianceStamped, f"{prefix}/pose_with_covariance", 10),
                              self.create_publisher(Image, f"{prefix}/debug_image", 1)))
        return parts

    # -- parameters at run time -------------------------------------------------------------

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """Refuse a change that EstimatorParams would not accept, or a confidence calibration
        file that cannot be used (rclpy has checked types, ranges and read-only already), with
        its reason: the estimators would refuse it under the worker."""
        flat = EstimatorParams().flat()
        try:
            changed = self.params.with_flat({p.name: p.value for p in parameters if p.name in flat})
            load_calibration(changed.pose.confidence_file)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        """Keep the new estimator parameters for the worker, which hands them to the
        estimators before its next image (a change must not reach an image in flight)."""
        flat = EstimatorParams().flat()
        updates = {p.name: p.value for p in parameters if p.name in flat}
        if updates:
            self.params = self.params.with_flat(updates)
            self.get_logger().info(f"estimator parameters changed, from the next image on: {updates}")

    # -- callbacks: store only --------------------------------------------------------------

    def _on_camera_info(self, msg: CameraInfo) -> None:
        self.camera_info = msg
        self._camera_info_arrived.set()

    def _on_image(self, msg: Image | CompressedImage) -> None:
        now = time.perf_counter()
        self.rate.add(now)
        self.frames.put((msg, now))

    def _follow_publishers(self) -> None:
        self.image_input.update()
        self.camera_info_input.update()

    def _heartbeat(self) -> None:
        """The input status, while no image arrives or while frames are being lost."""
        now = time.perf_counter()
        lost = self.image_input.lost - self._lost_reported
        self._lost_reported = self.image_input.lost
        silent_since = self.rate.last if self.rate.last is not None else self._started
        if lost == 0 and now - silent_since < HEARTBEAT_PERIOD:
            return
        topic = self.image_input.topic
        publishers = self.count_publishers(topic)
        values = {"publishers": publishers, "reliability": self.image_input.reliability_name,
                  "input_hz": self.rate.hz(now), "frames_lost": self.image_input.lost,
                  "seconds_without_image": now - silent_since}
        if lost:
            message = (f"{lost} frames lost on {topic} in the last {HEARTBEAT_PERIOD:g} s: large best-effort "
                       "images between processes need a reliable publisher or the shared-memory settings "
                       "of docs/ros.md")
            self._log_error("lost", message)
        elif self.rate.last is None:
            message = f"no image received on {topic} yet ({publishers} publishers)"
        else:
            message = f"no image on {topic} for {now - silent_since:.0f} s ({publishers} publishers)"
        status = diagnostic_status(f"{self.get_name()}: input", DiagnosticStatus.WARN, message, "", values)
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(array)

    def _log_error(self, cause: str, message: str) -> None:
        """An ERROR log line, at most one per cause every LOG_THROTTLE seconds."""
        now = time.monotonic()
        if now - self._logged.get(cause, -LOG_THROTTLE) >= LOG_THROTTLE:
            self._logged[cause] = now
            self.get_logger().error(message)

    # -- the worker -------------------------------------------------------------------------

    def _work(self) -> None:
        while (item := self.frames.take()) is not None:
            params = self.params
            for part in self.parts:
                if part.estimator.params is not params:
                    part.estimator.params = params
            try:
                self.process(*item, params)
            except Exception:  # e.g. a publish failing: log it, the next image may work
                self.get_logger().error(f"answering an image failed:\n{traceback.format_exc()}")

    def camera_for(self, height: int, width: int) -> Camera:
        """The latest CameraInfo, else the fallback intrinsics parameters; BadInput if neither.

        Image and CameraInfo travel on two topics, so a camera's first image can overtake its
        first CameraInfo: without a fallback the worker waits CAMERA_INFO_GRACE for one.
        """
        fx, fy, cx, cy = (float(self.get_parameter(n).value) for n in INTRINSICS)
        fallback = min(fx, fy, cx, cy) > 0
        if self.camera_info is None and not fallback:
            self._camera_info_arrived.wait(CAMERA_INFO_GRACE)
        info, refused = self.camera_info, ""
        camera = None
        if info is not None:
            try:
                camera = camera_from_info(info, self.get_parameter("input_is_rectified").value)
            except CameraError as exc:
                refused = f" (the last one was refused: {exc})"
        if camera is None:
            if not fallback:
                raise BadInput(f"no CameraInfo received on {self.camera_info_input.topic}{refused} "
                               "and no fallback intrinsics (parameters fx, fy, cx, cy)")
            return Camera(fx, fy, cx, cy, width, height)
        if (camera.width, camera.height) != (width, height):
            raise BadInput(f"CameraInfo is for {camera.width}x{camera.height} images but the image is {width}x{height}")
        return camera

    def process(self, msg: Image | CompressedImage, received: float, params: EstimatorParams | None = None) -> None:
        """Answer one image: a pose per found part and always one diagnostics array."""
        params = params or self.params
        statuses = []
        try:
            try:
                image = image_from_msg(msg, self.get_parameter("max_image_pixels").value)
            except ValueError as exc:
                raise BadInput(f"bad image: {exc}") from None
            camera = self.camera_for(*image.shape[:2])
        except BadInput as exc:
            self._log_error("input", str(exc))
            for part in self.parts:
                statuses.append(self._status(part, msg, DiagnosticStatus.ERROR, str(exc), {}, received))
        else:
            frame, edges_seconds = self._shared_frame(image, camera)
            statuses = self._part_threads.map(lambda part: self._estimate(part, msg, image, camera, received, params,
                                                                          frame, edges_seconds), self.parts)
        self.diagnostics_pub.publish(DiagnosticArray(header=msg.header, status=statuses))

    def _shared_frame(self, image: np.ndarray, camera: Camera) -> tuple[Any, float]:
        """With several parts, the image's edges found once for all (``Estimator.detect``: on a
        clean image they are most of a part's time) and the seconds that took; (None, 0) with
        one part, or when the detection fails: each part then meets the failure in its own
        ``estimate`` and reports it in its status."""
        if len(self.parts) < 2:
            return None, 0.0
        start = time.perf_counter()
        try:
            frame = self.parts[0].estimator.detect(image, camera, [part.estimator for part in self.parts[1:]])
        except Exception:
            return None, 0.0
        return frame, time.perf_counter() - start

    def _estimate(self, part: Part, msg, image: np.ndarray, camera: Camera, received: float,
                  params: EstimatorParams, frame=None, edges_seconds: float = 0.0) -> DiagnosticStatus:
        start = time.perf_counter()
        try:
            estimate = part.estimator.estimate(image, camera, frame=frame)
        except Exception as exc:  # a failure of one image must not stop the node
            self.get_logger().error(f"estimator failed on part {part.name}:\n{traceback.format_exc()}")
            return self._status(part, msg, DiagnosticStatus.ERROR, f"estimator failed: {exc!r}", {}, received)
        if frame is not None:  # the shared edges count in every part's time, as if it had found them
            estimate.timings["edges"] = edges_seconds
            if "total" in estimate.timings:
                estimate.timings["total"] += edges_seconds
        values = estimate_values(estimate)
        values["estimator_ms"] = 1000.0 * (time.perf_counter() - start + edges_seconds)
        if estimate.found:
            part.pose_pub.publish(pose_msg(estimate.R, estimate.t, msg.header))
            part.pose_covariance_pub.publish(pose_with_covariance_msg(
                estimate.R, estimate.t, estimate.covariance, msg.header))
        if self.get_parameter("debug_image").value and part.debug_pub.get_subscription_count() > 0:
            part.debug_pub.publish(image_msg(draw_overlay(image, estimate, part.name), msg.header))
        level, message = diagnose(estimate, params)
        return self._status(part, msg, level, message, values, received)

    def _status(self, part: Part, msg, level: bytes, message: str, values: dict, received: float) -> DiagnosticStatus:
        values = {**values, "latency_ms": 1000.0 * (time.perf_counter() - received),
                  "frames_skipped": self.frames.replaced, "frames_lost": self.image_input.lost,
                  "input_hz": self.rate.hz(time.perf_counter()), "version": __version__}
        return diagnostic_status(part.status_name, level, message, msg.header.frame_id, values)

    def destroy_node(self) -> None:
        """Stop the worker before the publishers it uses go away, then the estimators' threads."""
        if hasattr(self, "_worker"):
            self.frames.close()
            self._worker.join()
            self._part_threads.close()
            for part in self.parts:
                part.estimator.close()
        super().destroy_node()


def check_params_file(path: str | Path) -> None:
    """StartupError for a params file that is missing, not YAML, or sets a name the node does
    not declare (for this node, a namespaced ``/.../estimator`` or ``/**``): rclpy would
    silently ignore such a typo. Values are checked when the node declares them."""
    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except OSError as exc:
        raise StartupError(f"parameter file {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise StartupError(f"parameter file {path} is not a text file") from None
    except yaml.YAMLError as exc:
        raise StartupError(f"parameter file {path} is not valid YAML: {one_line(exc)}") from None
    if not isinstance(data, dict):
        raise StartupError(f"parameter file {path} must map node names to ros__parameters")
    known = set(NODE_PARAMETERS) | set(EstimatorParams().flat()) | {"use_sim_time"}

    def flatten(tree: dict, prefix: str = "") -> list[str]:
        names = []
        for key, value in tree.items():
            name = f"{prefix}{key}"
            names += flatten(value, f"{name}.") if isinstance(value, dict) else [name]
        return names

    names = []
    for node_key, section in data.items():
        if str(node_key) in (NODE_NAME, "/**") or str(node_key).endswith(f"/{NODE_NAME}"):
            if not isinstance(section, dict) or not isinstance(section.get("ros__parameters") or {}, dict):
                raise StartupError(f"parameter file {path}: {node_key} must hold a ros__parameters mapping")
            names += flatten(section.get("ros__parameters") or {})
    unknown = sorted(n for n in set(names) if n not in known and not n.startswith("qos_overrides."))
    if unknown:
        raise StartupError(f"parameter file {path} sets unknown parameter(s): {', '.join(unknown)}")


def ros_params_files(argv: list[str]) -> list[str]:
    """The files given as ``--params-file F`` inside ``--ros-args ... [--]`` sections."""
    files, in_ros_args = [], False
    for i, arg in enumerate(argv):
        if arg == "--ros-args":
            in_ros_args = True
        elif arg == "--":
            in_ros_args = False
        elif in_ros_args and arg == "--params-file" and i + 1 < len(argv):
            files.append(argv[i + 1])
    return files


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):
        self.exit(2, f"estimator: error: {message} (see estimator --help)\n")


NODE_EXAMPLE = """example:
  estimator --params-file config/node.yaml --ros-args -r image_raw:=/camera/image_raw \\
            -r camera_info:=/camera/camera_info
  (docs/tutorial.md, docs/ros.md)"""


def parse_args(argv: list[str]) -> tuple[list[str], argparse.Namespace]:
    """Split our own options from the ROS ones; ``--params-file F`` becomes
    ``--ros-args --params-file F`` since there is no ``ros2 run`` to do it."""
    parser = _Parser(prog="estimator", description=__doc__.splitlines()[0],
                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=NODE_EXAMPLE)
    parser.add_argument("--version", action="version", version=f"%(prog)s (brepose_ros) {__version__}")
    parser.add_argument("--params-file", action="append", default=[],
                        help="ROS parameters YAML (estimator: ros__parameters: ...), e.g. config/node.yaml")
    args = parser.parse_args(rclpy.utilities.remove_ros_args(argv)[1:])
    ros_args = list(argv)
    for path in args.params_file:
        ros_args += ["--ros-args", "--params-file", path]
    return ros_args, args


def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C or SIGTERM (rclpy's signal handlers shut the context down)."""
    argv = sys.argv if argv is None else argv
    ros_args, args = parse_args(argv)
    try:
        for path in [*args.params_file, *ros_params_files(argv)]:
            check_params_file(path)
    except StartupError as exc:
        print(f"estimator: error: cannot start: {exc}", file=sys.stderr)
        return 2
    try:
        rclpy.init(args=ros_args)
    except Exception as exc:  # rcl refuses malformed --ros-args with its own error types
        print(f"estimator: error: cannot start: bad ROS arguments: {one_line(exc)}", file=sys.stderr)
        return 2
    node = executor = None
    try:
        node = EstimatorNode()
        if not rclpy.ok():  # a signal during start-up: do not build an executor on a dead context
            raise ExternalShutdownException()
        executor = make_executor(node.get_parameter("executor_threads").value)
        executor.add_node(node)
        node.get_logger().info(f"estimating {', '.join(p.name for p in node.parts)} from "
                               f"{node.image_input.topic}")
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:
        if rclpy.ok():  # else a signal shut the context down while starting: a clean stop
            if not isinstance(exc, StartupError):
                raise
            print(f"estimator: error: cannot start: {exc}", file=sys.stderr)
            return 2
    finally:
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The rclpy adapter: images in, PoseStamped + diagnostics + a debug overlay out.

Topics (node name ``estimator``; relative names can be remapped with ``--ros-args -r``):

- in  ``image_raw`` (sensor_msgs/Image; mono8, mono16, bgr8, rgb8, bgra8, rgba8) and
  ``camera_info`` (sensor_msgs/CameraInfo), both sensor-data QoS with depth 1;
- out ``~/pose`` (geometry_msgs/PoseStamped, only when the part is found) and
  ``~/debug_image`` (sensor_msgs/Image bgr8, only while someone subscribes); with more than
  one part these become ``~/<part>/pose`` and ``~/<part>/debug_image``;
- out ``/diagnostics`` (diagnostic_msgs/DiagnosticArray): one array per image, header copied
  from the image, one status named ``estimator: <part>`` per part. Levels: OK = found with
  error ratio <= ``pose.warn_error_ratio``; WARN = not found (score below
  ``pose.min_score``) or error ratio above it; ERROR = the image or the intrinsics could not
  be used, or the estimator raised. Values: found, score, error_ratio, view_index,
  image_edges, matched_pairs, nearest_pairs, estimator_ms, latency_ms (receipt to answer),
  frames_skipped (frames received but replaced by a newer one before the worker got to them;
  frames the depth-1 DDS reader dropped itself are not seen), and the estimator's own stage
  timings as ``<stage>_ms``.

Threads: the subscription callbacks only store the newest frame; one worker thread runs the
estimator on it, so a slow image never builds a backlog. The executor threads
(``executor_threads``) keep callbacks and parameter services responsive meanwhile; the
estimator spreads the views of one image over its own ``matching.workers`` threads.
``messages.make_executor`` builds the executor with a work-around for a busy loop of rclpy
9.1's MultiThreadedExecutor.

Parameters: ``graphs``, ``part_names``, ``fx``/``fy``/``cx``/``cy``, ``executor_threads``,
``debug_image`` (see :data:`NODE_PARAMETERS`) and every estimator parameter under its
``params.EstimatorParams.flat()`` name (``matching.empty_coefficient``...). Estimator
parameters and the intrinsics can be changed at run time and apply from the next image.
"""
from __future__ import annotations

import argparse
import math
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
from geometry_msgs.msg import PoseStamped
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from ..aspect_graph import SUFFIX as GRAPH_SUFFIX
from ..aspect_graph import AspectGraph
from ..camera import Camera, CameraError
from ..online.estimator import Estimate, Estimator
from ..evaluation.overlay import draw_overlay
from ..params import EstimatorParams, field_docs
from ..image_codec import camera_from_info
from .messages import (DIAGNOSTICS_TOPIC, LATEST_ONLY, diagnostic_status, image_from_msg, image_msg,
                     make_executor, pose_msg)

NODE_NAME = "estimator"
INTRINSICS = ("fx", "fy", "cx", "cy")
#: seconds an image waits for the first CameraInfo when there are no fallback intrinsics
CAMERA_INFO_GRACE = 0.2
#: name -> (default, description, read_only); graphs and part names cannot change while running
NODE_PARAMETERS: dict[str, tuple[Any, str, bool]] = {
    "graphs": (Parameter.Type.STRING_ARRAY, "paths of precompiled aspect graphs (brepose-compile), one per part", True),
    "part_names": (Parameter.Type.STRING_ARRAY, "name of each graph's part, used in topics and diagnostics; "
                   "empty: the graph file names without .brepose.npz", True),
    "fx": (0.0, "fallback focal length x, pixels, used until a CameraInfo arrives; 0 = no fallback", False),
    "fy": (0.0, "fallback focal length y, pixels; 0 = no fallback", False),
    "cx": (0.0, "fallback principal point x, pixels; 0 = no fallback", False),
    "cy": (0.0, "fallback principal point y, pixels; 0 = no fallback", False),
    "executor_threads": (2, "threads of the MultiThreadedExecutor started by main()", True),
    "debug_image": (True, "publish the overlay image while ~/debug_image has subscribers", False),
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


@dataclass
class Part:
    """One part the node looks for: its estimator and its output topics."""

    name: str
    status_name: str
    estimator: Any
    pose_pub: Any
    debug_pub: Any


def diagnose(estimate: Estimate, params: EstimatorParams) -> tuple[bytes, str]:
    """Diagnostic level and message of one estimate (documented thresholds, module docstring)."""
    if not estimate.found:
        return DiagnosticStatus.WARN, (f"part not found (score {estimate.score:.2f}, "
                                       f"pose.min_score {params.pose.min_score:g})")
    if estimate.error_ratio > params.pose.warn_error_ratio:
        return DiagnosticStatus.WARN, (f"found, but error ratio {estimate.error_ratio:.2f} > "
                                       f"pose.warn_error_ratio {params.pose.warn_error_ratio:g}")
    return DiagnosticStatus.OK, f"found (score {estimate.score:.2f}, error ratio {estimate.error_ratio:.2f})"


def estimate_values(estimate: Estimate) -> dict[str, Any]:
    values = {"found": estimate.found, "score": float(estimate.score),
              "error_ratio": float(estimate.error_ratio), "view_index": estimate.view_index,
              "image_edges": estimate.n_image_segments, "matched_pairs": estimate.n_matched,
              "nearest_pairs": estimate.n_nearest}
    values.update({f"{stage}_ms": 1000.0 * float(s) for stage, s in estimate.timings.items()})
    return values


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
            self.parts = self._load_parts(estimator_factory, graph_loader)
        except StartupError:
            self.destroy_node()
            raise
        self.camera_info: Camera | None = None
        self.camera_info_error = ""
        self._camera_info_arrived = threading.Event()
        self.frames = NewestFrame()
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self.create_subscription(CameraInfo, "camera_info", self._on_camera_info, LATEST_ONLY)
        self.create_subscription(Image, "image_raw", self._on_image, LATEST_ONLY)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self._worker = threading.Thread(target=self._work, name="estimator-worker", daemon=True)
        self._worker.start()

    # -- start-up ---------------------------------------------------------------------------

    def _declare_parameters(self) -> None:
        docs = field_docs()
        declarations = [(name, default, description, read_only)
                        for name, (default, description, read_only) in NODE_PARAMETERS.items()]
        declarations += [(name, value, docs[name], False) for name, value in EstimatorParams().flat().items()]
        for name, default, description, read_only in declarations:
            try:
                self.declare_parameter(name, default, ParameterDescriptor(description=description, read_only=read_only))
            except Exception as exc:  # rclpy raises several types for a bad override value
                raise StartupError(f"parameter {name}: {exc}") from None

    def _estimator_params(self) -> EstimatorParams:
        names = EstimatorParams().flat()
        try:
            return EstimatorParams().with_flat({n: self.get_parameter(n).value for n in names})
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
                              self.create_publisher(Image, f"{prefix}/debug_image", 1)))
        return parts

    # -- parameters at run time -------------------------------------------------------------

    def _validate_parameters(self, parameters: list[Parameter]) -> SetParametersResult:
        """Refuse a change that EstimatorParams (or the intrinsics check) would not accept."""
        flat = EstimatorParams().flat()
        try:
            self.params.with_flat({p.name: p.value for p in parameters if p.name in flat})
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        for p in parameters:
            if p.name in INTRINSICS and not (math.isfinite(p.value) and p.value >= 0):
                return SetParametersResult(successful=False, reason=f"{p.name} must be finite and >= 0, got {p.value}")
        return SetParametersResult(successful=True)

    def _apply_parameters(self, parameters: list[Parameter]) -> None:
        """Hand the new thresholds to every estimator; they take effect from the next image."""
        flat = EstimatorParams().flat()
        updates = {p.name: p.value for p in parameters if p.name in flat}
        if updates:
            self.params = self.params.with_flat(updates)
            for part in self.parts:
                part.estimator.params = self.params
            self.get_logger().info(f"estimator parameters changed: {updates}")

    # -- callbacks: store only --------------------------------------------------------------

    def _on_camera_info(self, msg: CameraInfo) -> None:
        try:
            self.camera_info, self.camera_info_error = camera_from_info(msg), ""
        except CameraError as exc:
            self.camera_info, self.camera_info_error = None, str(exc)
        self._camera_info_arrived.set()

    def _on_image(self, msg: Image) -> None:
        self.frames.put((msg, time.perf_counter()))

    # -- the worker -------------------------------------------------------------------------

    def _work(self) -> None:
        while (item := self.frames.take()) is not None:
            try:
                self.process(*item)
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
        camera = self.camera_info
        if camera is None:
            if not fallback:
                refused = f" (the last one was refused: {self.camera_info_error})" if self.camera_info_error else ""
                raise BadInput(f"no CameraInfo received on {self.resolve_topic_name('camera_info')}{refused} "
                               "and no fallback intrinsics (parameters fx, fy, cx, cy)")
            return Camera(fx, fy, cx, cy, width, height)
        if (camera.width, camera.height) != (width, height):
            raise BadInput(f"CameraInfo is for {camera.width}x{camera.height} images but the image is {width}x{height}")
        return camera

    def process(self, msg: Image, received: float) -> None:
        """Answer one image: a pose per found part and always one diagnostics array."""
        statuses = []
        try:
            try:
                image = image_from_msg(msg)
            except ValueError as exc:
                raise BadInput(f"bad image: {exc}") from None
            camera = self.camera_for(*image.shape[:2])
        except BadInput as exc:
            for part in self.parts:
                statuses.append(self._status(part, msg, DiagnosticStatus.ERROR, str(exc), {}, received))
        else:
            statuses = [self._estimate(part, msg, image, camera, received) for part in self.parts]
        self.diagnostics_pub.publish(DiagnosticArray(header=msg.header, status=statuses))

    def _estimate(self, part: Part, msg: Image, image: np.ndarray, camera: Camera, received: float) -> DiagnosticStatus:
        start = time.perf_counter()
        try:
            estimate = part.estimator.estimate(image, camera)
        except Exception as exc:  # a failure of one image must not stop the node
            self.get_logger().error(f"estimator failed on part {part.name}:\n{traceback.format_exc()}")
            return self._status(part, msg, DiagnosticStatus.ERROR, f"estimator failed: {exc!r}", {}, received)
        values = estimate_values(estimate)
        values["estimator_ms"] = 1000.0 * (time.perf_counter() - start)
        if estimate.found:
            part.pose_pub.publish(pose_msg(estimate.R, estimate.t, msg.header))
        if self.get_parameter("debug_image").value and part.debug_pub.get_subscription_count() > 0:
            part.debug_pub.publish(image_msg(draw_overlay(image, estimate, part.name), msg.header))
        level, message = diagnose(estimate, self.params)
        return self._status(part, msg, level, message, values, received)

    def _status(self, part: Part, msg: Image, level: bytes, message: str, values: dict, received: float) -> DiagnosticStatus:
        values = {**values, "latency_ms": 1000.0 * (time.perf_counter() - received),
                  "frames_skipped": self.frames.replaced}
        return diagnostic_status(part.status_name, level, message, msg.header.frame_id, values)

    def destroy_node(self) -> None:
        """Stop the worker before the publishers it uses go away, then the estimators' threads."""
        if hasattr(self, "_worker"):
            self.frames.close()
            self._worker.join()
            for part in self.parts:
                part.estimator.close()
        super().destroy_node()


def check_params_file(path: str | Path) -> None:
    """StartupError for a params file that is missing, not YAML, or sets a name the node does
    not declare (for this node or ``/**``): rclpy would silently ignore such a typo."""
    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except OSError as exc:
        raise StartupError(f"parameter file {path}: {exc.strerror}") from None
    except yaml.YAMLError as exc:
        raise StartupError(f"parameter file {path} is not valid YAML: {exc}") from None
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
    for node_key in (NODE_NAME, f"/{NODE_NAME}", "/**"):
        names += flatten((data.get(node_key) or {}).get("ros__parameters") or {})
    unknown = sorted(n for n in set(names) if n not in known and not n.startswith("qos_overrides."))
    if unknown:
        raise StartupError(f"parameter file {path} sets unknown parameter(s): {', '.join(unknown)}")


def parse_args(argv: list[str]) -> tuple[list[str], argparse.Namespace]:
    """Split our own options from the ROS ones; ``--params-file F`` becomes
    ``--ros-args --params-file F`` since there is no ``ros2 run`` to do it."""
    parser = argparse.ArgumentParser(prog="estimator", description=__doc__.splitlines()[0])
    parser.add_argument("--params-file", action="append", default=[],
                        help="ROS parameters YAML (estimator: ros__parameters: ...), e.g. config/node.yaml")
    args = parser.parse_args(rclpy.utilities.remove_ros_args(argv)[1:])
    ros_args = list(argv)
    for path in args.params_file:
        ros_args += ["--ros-args", "--params-file", path]
    return ros_args, args


def main(argv: list[str] | None = None) -> int:
    """Run the node until Ctrl-C or SIGTERM (rclpy's signal handlers shut the context down)."""
    ros_args, args = parse_args(sys.argv if argv is None else argv)
    try:
        for path in args.params_file:
            check_params_file(path)
    except StartupError as exc:
        print(f"estimator: cannot start: {exc}", file=sys.stderr)
        return 2
    rclpy.init(args=ros_args)
    node = executor = None
    try:
        node = EstimatorNode()
        if not rclpy.ok():  # a signal during start-up: do not build an executor on a dead context
            raise ExternalShutdownException()
        executor = make_executor(node.get_parameter("executor_threads").value)
        executor.add_node(node)
        node.get_logger().info(f"estimating {', '.join(p.name for p in node.parts)} from "
                               f"{node.resolve_topic_name('image_raw')}")
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:
        if rclpy.ok():  # else a signal shut the context down while starting: a clean stop
            if not isinstance(exc, StartupError):
                raise
            print(f"estimator: cannot start: {exc}", file=sys.stderr)
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

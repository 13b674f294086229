"""Replay tools: feed frames into the node's topics and collect what it answers.

:class:`RosSession` spins nodes in a background thread; :class:`Player` and
:class:`PoseRecorder` are the two halves of a replay (the launch-free scripts, the demo, the
benchmark and the tests use them).
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Iterator

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.node import Node
from rclpy.qos import ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from ..scene_folder import load_scene
from .bags import read_bag
from .messages import (COMPRESSED_SUFFIX, DIAGNOSTICS_TOPIC, PUBLISHER_QOS, camera_info_msg, compressed_image_msg,
                       image_msg, make_executor, pose_from_msg, stamp_from_ns, stamp_ns, status_values)

TRANSPORTS = ("raw", "compressed")
#: how long a player waits for the node's subscription to follow its reliability once
#: matched (the node follows its publishers within a quarter of a second, node.py)
QOS_SETTLE = 2.0


def bag_frames(bag: str | Path, topic: str | None = None, info_topic: str | None = None,
               transport: str = "raw") -> Iterator[tuple]:
    """``(stamp_ns, Image or CompressedImage, CameraInfo or None)`` messages of a bag for
    :class:`Player`, with the recorded headers. ``raw`` re-encodes ``bags.read_bag``'s arrays
    (mono8, mono16 and bgr8 stay as they were, other encodings arrive as bgr8);
    ``compressed`` replays recorded CompressedImage data unchanged and PNG-encodes the rest."""
    if transport not in TRANSPORTS:
        raise ValueError(f"transport must be one of {', '.join(TRANSPORTS)}, got {transport!r}")
    for frame in read_bag(bag, topic, info_topic):
        header = Header(stamp=stamp_from_ns(frame.stamp_ns), frame_id=frame.frame_id)
        info = camera_info_msg(frame.camera, header) if frame.camera is not None else None
        if transport == "raw":
            image = image_msg(frame.image, header)
        elif frame.compressed is not None:
            image = CompressedImage(header=header, format=frame.compressed[0], data=frame.compressed[1])
        else:
            image = compressed_image_msg(frame.image, header)
        yield frame.stamp_ns, image, info


class RosSession:
    """A private rclpy context whose executor spins in a background thread, so the caller's
    thread is free to publish and wait (scripts, the demo, the benchmark, tests).

    ``close`` stops the spin loop first and only then shuts the executor down, destroys the
    nodes and the context, the order that keeps the process from aborting at exit
    (../shared/ROS2_ON_PIP.md): rclpy 9.1's ``Executor.shutdown`` does not wait for callbacks
    in flight, which then hit its destroyed guard condition (InvalidHandle tracebacks).
    """

    def __init__(self, threads: int = 2, executor_factory: Callable = make_executor):
        self.context = Context()
        rclpy.init(context=self.context)
        self.executor = executor_factory(threads, context=self.context)
        self.nodes: list[Node] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="ros-executor", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self.context.ok():
            self.executor.spin_once(timeout_sec=0.1)

    def add(self, node: Node) -> Node:
        self.nodes.append(node)
        self.executor.add_node(node)
        return node

    def node(self, name: str) -> Node:
        return self.add(Node(name, context=self.context))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10.0)
        self.executor.shutdown()
        for node in reversed(self.nodes):
            node.destroy_node()
        rclpy.shutdown(context=self.context)

    def __enter__(self) -> "RosSession":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def wait_until(predicate: Callable, timeout: float, what: str):
    """The first truthy value of ``predicate()``, polled every 5 ms; TimeoutError naming ``what``."""
    deadline = time.monotonic() + timeout
    while not (result := predicate()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.005)
    return result


class DiagnosticsListener:
    """Every diagnostics array and its arrival time by image stamp; a caller can wait for one.
    ``statuses`` collects the statuses of every array of a stamp: several estimator processes
    (launch_free_scripts/run_partitioned.py) each answer the same image."""

    def __init__(self, node: Node, topic: str = DIAGNOSTICS_TOPIC):
        self._cond = threading.Condition()
        self.by_stamp: dict[int, DiagnosticArray] = {}
        self.arrived: dict[int, float] = {}
        self.statuses: dict[int, list] = {}
        self.subscription = node.create_subscription(DiagnosticArray, topic, self._on_message, 50)

    def _on_message(self, msg: DiagnosticArray) -> None:
        with self._cond:
            stamp = stamp_ns(msg.header.stamp)
            self.by_stamp[stamp] = msg
            self.arrived[stamp] = time.perf_counter()
            self.statuses.setdefault(stamp, []).extend(msg.status)
            self._cond.notify_all()

    def wait_for(self, stamp: int, timeout: float, statuses: int = 1) -> DiagnosticArray | None:
        """The last array of ``stamp`` once ``statuses`` statuses of it have arrived (None
        after ``timeout``)."""
        with self._cond:
            if self._cond.wait_for(lambda: len(self.statuses.get(stamp, ())) >= statuses, timeout):
                return self.by_stamp[stamp]
            return None


@dataclass
class Playback:
    """What a replay sent and when, and which images the node answered (diagnostics)."""

    published_at: dict[int, float] = field(default_factory=dict)
    seconds: float = 0.0

    def answered(self, diagnostics: DiagnosticsListener, statuses: int = 1) -> list[int]:
        return [s for s in self.published_at if len(diagnostics.statuses.get(s, ())) >= statuses]

    def latencies_ms(self, diagnostics: DiagnosticsListener) -> dict[int, float]:
        """Publish-to-diagnostics time of every answered image, by stamp."""
        arrived = diagnostics.arrived
        return {s: 1000.0 * (arrived[s] - t) for s, t in self.published_at.items() if s in arrived}


class Player:
    """Publishes Image (or CompressedImage) + CameraInfo frames into the node's input topics.

    A frame is ``(stamp_ns, Image or CompressedImage, CameraInfo or None)`` (see
    :func:`bag_frames`); ``transport`` ``compressed`` publishes on ``<image_topic>/compressed``.
    ``reliability`` is what the player offers: ``best_effort`` as camera drivers do, or
    ``reliable``, which large frames need between processes (docs/ros.md).
    ``lockstep`` waits after each image for the node's diagnostics of that image (same header
    stamp), so replay runs exactly as fast as the node keeps up and no frame is lost;
    ``rate`` keeps the recorded spacing of the stamps divided by ``speed``, like
    ``ros2 bag play``, and the node drops what it cannot keep up with, as it would live.
    ``statuses`` is the number of diagnostics statuses that answer one image (its parts, over
    every estimator process): lock-step waits for all of them.
    """

    def __init__(self, node: Node, image_topic: str = "image_raw", info_topic: str = "camera_info",
                 diagnostics: DiagnosticsListener | None = None, reliability: str = "best_effort",
                 transport: str = "raw", statuses: int = 1):
        if reliability not in PUBLISHER_QOS:
            raise ValueError(f"reliability must be one of {', '.join(PUBLISHER_QOS)}, got {reliability!r}")
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {', '.join(TRANSPORTS)}, got {transport!r}")
        self.node = node
        qos = PUBLISHER_QOS[reliability]
        if transport == "compressed":
            self.image_pub = node.create_publisher(CompressedImage, image_topic + COMPRESSED_SUFFIX, qos)
        else:
            self.image_pub = node.create_publisher(Image, image_topic, qos)
        self.info_pub = node.create_publisher(CameraInfo, info_topic, qos)
        self.reliable = reliability == "reliable"
        self.diagnostics = diagnostics or DiagnosticsListener(node)
        self.statuses = statuses

    def wait_for_node(self, timeout: float = 10.0, nodes: int = 1) -> None:
        """Wait until ``nodes`` nodes subscribe to the images and we to their diagnostics, and
        give the nodes' subscriptions a moment to follow the player's reliability: a node left
        reliable by an earlier reliable player does not match a best-effort one, and the frames
        published meanwhile vanish without the reader knowing of them (nor reporting them lost)."""
        wait_until(lambda: self.image_pub.get_subscription_count() >= nodes
                   and self.diagnostics.subscription.get_publisher_count() >= nodes,
                   timeout, f"{nodes} node(s) subscribed to {self.image_pub.topic_name} and publishing diagnostics")
        try:
            wait_until(self._subscribers_follow, QOS_SETTLE, "subscriptions following the player's reliability")
        except TimeoutError:
            pass  # a node told to keep its reliability: it still gets what its QoS matches

    def _subscribers_follow(self) -> bool:
        wanted = ReliabilityPolicy.RELIABLE if self.reliable else ReliabilityPolicy.BEST_EFFORT
        infos = self.node.get_subscriptions_info_by_topic(self.image_pub.topic_name)
        return bool(infos) and all(i.qos_profile.reliability == wanted for i in infos)

    def play(self, frames: Iterable, mode: str = "lockstep", speed: float = 1.0,
             timeout: float = 10.0) -> Playback:
        """Replay ``frames`` in order; in lock-step an image not answered within ``timeout``
        is left behind (it shows as unanswered in the result)."""
        if mode not in ("lockstep", "rate"):
            raise ValueError(f"mode must be 'lockstep' or 'rate', got {mode!r}")
        playback = Playback()
        start = time.perf_counter()
        first = None
        for stamp, image, info in frames:
            if mode == "rate":
                first = stamp if first is None else first
                delay = start + (stamp - first) / 1e9 / speed - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            if info is not None:
                self.info_pub.publish(info)
            playback.published_at[stamp] = time.perf_counter()
            self.image_pub.publish(image)
            if mode == "lockstep":
                self.diagnostics.wait_for(stamp, timeout, self.statuses)
        playback.seconds = time.perf_counter() - start
        return playback


class PoseRecorder:
    """Collects one part's answers as CONVENTIONS.md predictions.

    The pose comes from the PoseStamped, score and error ratio from the part's diagnostics
    status of the same image (same header stamp); ``status_name`` None takes an array's only
    status (a node with one part). Images answered with ERROR (unusable input) are left out;
    images where the part was not found get ``R``/``t`` null.
    """

    def __init__(self, node: Node, pose_topic: str, status_name: str | None = None,
                 diagnostics: DiagnosticsListener | None = None):
        self.status_name = status_name
        self.poses: dict[int, PoseStamped] = {}
        self.diagnostics = diagnostics or DiagnosticsListener(node)
        self.subscription = node.create_subscription(PoseStamped, pose_topic, self._on_pose, 50)

    def _on_pose(self, msg: PoseStamped) -> None:
        self.poses[stamp_ns(msg.header.stamp)] = msg

    def wait_for_node(self, timeout: float) -> bool:
        """Whether the node's pose and diagnostics publishers matched ours within ``timeout`` s:
        a pose published before they match is lost to this recorder."""
        try:
            wait_until(lambda: self.subscription.get_publisher_count() >= 1
                       and self.diagnostics.subscription.get_publisher_count() >= 1,
                       timeout, "the estimator's pose and diagnostics")
        except TimeoutError:
            return False
        return True

    def values(self, stamp: int) -> dict[str, str]:
        """The diagnostics values of the part for one image ({} if it has none)."""
        statuses = list(self.diagnostics.by_stamp[stamp].status) if stamp in self.diagnostics.by_stamp else []
        if self.status_name is None:
            statuses = statuses if len(statuses) == 1 else []
        else:
            statuses = [s for s in statuses if s.name == self.status_name]
        return status_values(statuses[0]) if statuses else {}

    def predictions(self, names: dict[int, str] | None = None) -> list[dict]:
        """One entry per answered image in stamp order; ``names`` maps stamps to image paths."""
        out = []
        for stamp in sorted(self.diagnostics.by_stamp):
            values = self.values(stamp)
            if "score" not in values:
                continue
            entry = {"image": (names or {}).get(stamp, f"stamp:{stamp}"), "R": None, "t": None,
                     "score": float(values["score"]), "error_ratio": float(values["error_ratio"])}
            if values["found"] == "True":
                R, t = pose_from_msg(wait_until(lambda: self.poses.get(stamp), 5.0, f"the pose of image {stamp}"))
                entry["R"], entry["t"] = R.ravel().tolist(), t.tolist()
            out.append(entry)
        return out


def scene_names(bag: str | Path, scene: str | Path) -> dict[int, str]:
    """Image stamps of a bag written from a scene (``bags.write_scene_bag``, gt.json order)
    mapped to the scene's image paths, so recorded poses can be graded against gt.json."""
    stamps = [frame.stamp_ns for frame in read_bag(bag)]
    entries = load_scene(scene).entries
    if len(stamps) != len(entries):
        raise ValueError(f"{bag} holds {len(stamps)} images but scene {scene} has {len(entries)}: "
                         "the bag was not written from this scene")
    return {stamp: entry.image for stamp, entry in zip(stamps, entries)}

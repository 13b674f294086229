"""In-process rclpy harness for the node tests (../shared/ROS2_ON_PIP.md): a fresh context per
test with the node's own executor spinning in a daemon thread (``ros.replay.RosSession``), and a
probe node that publishes images and collects what the estimator node answers.
"""
from __future__ import annotations

import os
from pathlib import Path

# discovery off: nodes in this process still talk, other developers' test runs are not heard
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")

import numpy as np  # noqa: E402
from diagnostic_msgs.msg import DiagnosticStatus  # noqa: E402
from geometry_msgs.msg import PoseStamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from brepose_ros.camera import Camera  # noqa: E402
from brepose_ros.ros.node import EstimatorNode  # noqa: E402
from brepose_ros.ros.messages import SENSOR_QOS, camera_info_msg, image_msg, stamp_from_ns, stamp_ns  # noqa: E402
from brepose_ros.ros.replay import DiagnosticsListener, RosSession, wait_until  # noqa: E402

TIMEOUT = 10.0
FRAME = "camera_optical_frame"
REPO = Path(__file__).resolve().parents[1]


def ros_env(**extra) -> dict:
    """The environment of a node or tool in another process: discovery on (two processes talk;
    give a random ROS_DOMAIN_ID so that parallel runs do not hear each other), the ROS wheels'
    bootstrap variables cleared (../shared/ROS2_ON_PIP.md), the clone importable."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "_ROS_WHEELS_BOOTSTRAP_COMPLETE", "LD_LIBRARY_PATH")}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    return {**env, **extra}


class Harness(RosSession):
    """One test's ROS world: context, executor thread and the probe node."""

    def __init__(self):
        super().__init__()
        self.probe = self.node("probe")
        self.image_pub = self.probe.create_publisher(Image, "image_raw", SENSOR_QOS)
        self.info_pub = self.probe.create_publisher(CameraInfo, "camera_info", SENSOR_QOS)
        self.diagnostics = DiagnosticsListener(self.probe)
        self.poses: dict[int, PoseStamped] = {}
        self._next_stamp = 1_000_000_000

    def start_node(self, parameters: dict, **kwargs) -> EstimatorNode:
        """An EstimatorNode in this context, with every topic matched before returning (the
        probe's images only when the node listens to them and follows its best effort)."""
        overrides = [Parameter(name, value=value) for name, value in parameters.items()]
        node = self.add(EstimatorNode(context=self.context, parameter_overrides=overrides, **kwargs))
        for part in node.parts:
            self.probe.create_subscription(PoseStamped, part.pose_pub.topic_name, self._on_pose, 10)
            wait_until(lambda p=part: p.pose_pub.get_subscription_count() > 0, TIMEOUT, "pose subscription")
        if node.image_input.topic == self.image_pub.topic_name and node.image_input.follows_publishers:
            wait_until(lambda: self.image_pub.get_subscription_count() > 0, TIMEOUT, "image subscription")
        wait_until(lambda: node.diagnostics_pub.get_subscription_count() > 0, TIMEOUT, "diagnostics subscription")
        return node

    def _on_pose(self, msg: PoseStamped) -> None:
        self.poses[stamp_ns(msg.header.stamp)] = msg

    def header(self) -> Header:
        self._next_stamp += 33_000_123
        return Header(stamp=stamp_from_ns(self._next_stamp), frame_id=FRAME)

    def publish(self, image: np.ndarray | Image, camera: Camera | None = None) -> int:
        """Publish an image (ndarray or a ready message, re-stamped) and its CameraInfo; its stamp."""
        header = self.header()
        msg = image_msg(image, header) if isinstance(image, np.ndarray) else image
        msg.header = header
        if camera is not None:
            self.info_pub.publish(camera_info_msg(camera, header))
        self.image_pub.publish(msg)
        return self._next_stamp

    def answer(self, stamp: int, timeout: float = TIMEOUT) -> list[DiagnosticStatus]:
        """The diagnostics statuses of one image, waiting for them."""
        array = self.diagnostics.wait_for(stamp, timeout)
        if array is None:
            raise TimeoutError(f"no diagnostics for image stamp {stamp} within {timeout} s")
        return list(array.status)

    def pose(self, stamp: int, timeout: float = TIMEOUT) -> PoseStamped:
        return wait_until(lambda: self.poses.get(stamp), timeout, f"pose of image {stamp}")

"""The ROS node in-process: topics, diagnostics levels, bad input, parameters, start-up errors.

The first tests run the real pipeline on a coarse aspect graph of the sample part and a
rendered image; the others inject a fake estimator to reach cases (exceptions, slow frames,
several parts) quickly and exactly.
"""
from __future__ import annotations

import os
import random
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticStatus
from rcl_interfaces.msg import ParameterType
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.parameter import Parameter
from rclpy.qos import ReliabilityPolicy
from sensor_msgs.msg import CompressedImage, Image

from brepose_ros.offline.compiler import compile_aspect_graph
from brepose_ros.camera import Camera
from brepose_ros.online.estimator import Estimate
from brepose_ros.geometry import matrix_from_quaternion, rotation_angle_deg
from brepose_ros.ros.node import StartupError, check_params_file, main
from brepose_ros.params import EstimatorParams
from brepose_ros.evaluation.overlay import FOUND as FOUND_COLOUR
from brepose_ros.ros.messages import (PUBLISHER_QOS, camera_info_msg, compressed_image_msg, image_from_msg, image_msg,
                                      pose_from_msg, stamp_ns, status_values)
from brepose_ros.ros.replay import wait_until
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene
from node_helpers import FRAME, TIMEOUT, Harness

pytestmark = pytest.mark.ros

CONFIG = Path(__file__).resolve().parents[1] / "config"
CAMERA = Camera(200.0, 200.0, 79.5, 59.5, 160, 120)
R_FAKE = matrix_from_quaternion(np.array([0.1, -0.2, 0.3, 0.9]))
T_FAKE = np.array([0.01, -0.02, 0.4])
SEGMENTS = np.array([[[50.0, 40.0], [110.0, 40.0]], [[50.0, 80.0], [110.0, 80.0]]])


class FakeEstimator:
    """Finds "the part" in any image with a bright pixel; records the parameters it ran with."""

    def __init__(self, graph, params, delay: float = 0.0, fail: bool = False):
        self.graph, self.params, self.delay, self.fail = graph, params, delay, fail
        self.calls: list[tuple[tuple, Camera, object]] = []
        self.frames: list = []  # the frame each call was handed (None: found its own edges)
        self.detected: list = []  # the estimators each ``detect`` was for besides this one

    def detect(self, image: np.ndarray, camera: Camera, others=()):
        self.detected.append(list(others))
        return ("frame", image.shape)

    def estimate(self, image: np.ndarray, camera: Camera, frame=None) -> Estimate:
        self.calls.append((image.shape, camera, self.params))
        self.frames.append(frame)
        time.sleep(self.delay)
        if self.fail:
            raise RuntimeError("boom")
        found = bool(image.max() > 0)
        return Estimate(found, R_FAKE if found else None, T_FAKE if found else None,
                        score=0.9 if found else 0.1, error_ratio=0.2, view_index=3,
                        confidence=0.8 if found else 0.05, n_image_segments=12, n_matched=8, n_nearest=6,
                        timings={"edges": 0.001},
                        image_segments=SEGMENTS, model_segments=SEGMENTS + 1.0)

    def close(self) -> None:
        pass


class WatchedEstimator(FakeEstimator):
    """A slow FakeEstimator that records every parameter hand-over made while it was estimating."""

    def __init__(self, graph, params):
        self.busy, self.changed_while_busy = False, []
        super().__init__(graph, params, delay=0.3)

    @property
    def params(self):
        return self._params

    @params.setter
    def params(self, value):
        if getattr(self, "busy", False):
            self.changed_while_busy.append(value)
        self._params = value

    def estimate(self, image, camera, frame=None):
        self.busy = True
        try:
            return super().estimate(image, camera, frame)
        finally:
            self.busy = False


def fake_loader(path: str):
    if not path.endswith(".brepose.npz"):
        raise ValueError(f"{path} is not an aspect graph file")
    return path


@pytest.fixture
def ros():
    harness = Harness()
    yield harness
    harness.close()


def start(ros: Harness, factory=FakeEstimator, **parameters):
    """The node with fake graphs and estimators; ``graphs=None`` leaves the parameter unset."""
    parameters = {"graphs": ["bracket.brepose.npz"], **parameters}
    parameters = {name: value for name, value in parameters.items() if value is not None}
    return ros.start_node(parameters, estimator_factory=factory, graph_loader=fake_loader)


def part_image(encoding_shape=(120, 160, 3), dtype=np.uint8) -> np.ndarray:
    image = np.zeros(encoding_shape, dtype=dtype)
    image[40:80, 50:110] = np.iinfo(dtype).max // 2
    return image


@pytest.fixture(scope="session")
def sample(sample_step, tmp_path_factory):
    """A coarse (20 degree) aspect graph of the sample part and a rendered image with its pose."""
    folder = tmp_path_factory.mktemp("node_sample")
    graph = compile_aspect_graph(sample_step, step_deg=20.0, workers=1, progress=False)
    path = graph.save(folder / "sample_bracket.brepose.npz")
    scene = generate_scene(sample_step, folder / "scene", 3, seed=1,
                           config=SceneConfig(width=320, height=240, fx=300.0))
    truth = scene.entries[2]
    return SimpleNamespace(graph=path, camera=scene.camera, truth=truth, diameter=graph.model_diameter,
                           image=cv2.imread(str(truth.path), cv2.IMREAD_UNCHANGED))


def start_real(ros: Harness, sample, **parameters):
    return ros.start_node({"graphs": [str(sample.graph)], **parameters})


def test_real_pipeline_publishes_the_pose_with_the_image_stamp(ros, sample):
    start_real(ros, sample)
    stamp = ros.publish(sample.image, sample.camera)
    pose = ros.pose(stamp)
    assert pose.header.frame_id == FRAME
    R, t = pose_from_msg(pose)
    assert rotation_angle_deg(R, sample.truth.R) < 5.0
    assert np.linalg.norm(t - sample.truth.t) < 0.05 * sample.diameter
    [status] = ros.answer(stamp)
    assert status.name == "estimator: sample_bracket" and status.level in (DiagnosticStatus.OK, DiagnosticStatus.WARN)
    values = status_values(status)
    assert values["found"] == "True" and 0.0 <= float(values["error_ratio"]) <= 1.0
    assert int(values["image_edges"]) > 0 and int(values["matched_pairs"]) > 0


def test_real_pipeline_warns_without_the_part_and_recovers_from_a_bad_image(ros, sample):
    start_real(ros, sample)
    blank = ros.publish(np.full(sample.image.shape, 90, np.uint8), sample.camera)
    [status] = ros.answer(blank)
    assert status.level == DiagnosticStatus.WARN and "not found" in status.message
    [status] = ros.answer(ros.publish(raw_image("mono8", 240, 320, 300, 300 * 240), sample.camera))
    assert status.level == DiagnosticStatus.ERROR and "step" in status.message
    ros.pose(ros.publish(sample.image, sample.camera))
    assert blank not in ros.poses


def test_real_pipeline_takes_a_new_threshold_without_restart(ros, sample):
    node = start_real(ros, sample)
    assert node.set_parameters([Parameter("pose.min_score", value=0.999)])[0].successful
    [status] = ros.answer(ros.publish(sample.image, sample.camera))
    assert status.level == DiagnosticStatus.WARN and "pose.min_score 0.999" in status.message


def test_console_script_stops_cleanly_on_sigterm(sample, tmp_path):
    params = tmp_path / "node.yaml"
    params.write_text(f"estimator:\n  ros__parameters:\n    graphs: [{sample.graph}]\n")
    env = {**os.environ, "ROS_DOMAIN_ID": str(random.randint(100, 200))}
    env.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)
    process = subprocess.Popen([sys.executable, "-m", "brepose_ros.ros.node", "--params-file", str(params)],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, text=True)
    try:
        assert "estimating sample_bracket" in process.stdout.readline()
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=TIMEOUT) == 0
        assert "terminate called" not in process.stdout.read()
    finally:
        process.kill()


def test_pose_and_diagnostics_carry_the_image_stamp(ros):
    node = start(ros)
    stamp = ros.publish(part_image(), CAMERA)
    pose = ros.pose(stamp)
    assert pose.header.frame_id == FRAME
    R, t = pose_from_msg(pose)
    np.testing.assert_allclose(R, R_FAKE, atol=1e-9)
    np.testing.assert_allclose(t, T_FAKE)
    [status] = ros.answer(stamp)
    assert status.level == DiagnosticStatus.OK and status.name == "estimator: bracket"
    assert status.hardware_id == FRAME
    values = status_values(status)
    assert float(values["error_ratio"]) == pytest.approx(0.2)
    assert float(values["confidence"]) == pytest.approx(0.8)
    for key in ("score", "view_index", "image_edges", "matched_pairs", "latency_ms", "estimator_ms", "edges_ms"):
        assert key in values
    assert node.parts[0].estimator.calls[0][1] == CAMERA


@pytest.mark.parametrize("shape, dtype", [((120, 160), np.uint8), ((120, 160), np.uint16), ((120, 160, 4), np.uint8)])
def test_other_pixel_formats_are_accepted(ros, shape, dtype):
    start(ros)
    stamp = ros.publish(part_image(shape, dtype), CAMERA)
    assert ros.answer(stamp)[0].level == DiagnosticStatus.OK


def test_image_without_the_part_gives_warn_and_no_pose(ros):
    start(ros)
    stamp = ros.publish(np.zeros((120, 160), np.uint8), CAMERA)
    [status] = ros.answer(stamp)
    assert status.level == DiagnosticStatus.WARN and "not found" in status.message
    assert status_values(status)["found"] == "False"
    time.sleep(0.2)
    assert stamp not in ros.poses


def raw_image(encoding: str, height: int, width: int, step: int, size: int) -> Image:
    return Image(encoding=encoding, height=height, width=width, step=step, data=bytes(size))


@pytest.mark.parametrize("bad", [
    raw_image("32FC1", 120, 160, 640, 640 * 120),
    raw_image("bgr8", 120, 160, 400, 400 * 120),   # wrong step
    raw_image("mono8", 120, 160, 160, 100),         # data too short
    raw_image("mono8", 0, 0, 0, 0),                 # empty
], ids=["encoding", "step", "size", "empty"])
def test_bad_image_gives_error_and_the_node_goes_on(ros, bad):
    start(ros)
    [status] = ros.answer(ros.publish(bad, CAMERA))
    assert status.level == DiagnosticStatus.ERROR and status.message.startswith("bad image")
    good = ros.publish(part_image(), CAMERA)
    ros.pose(good)


def test_missing_camera_info_is_an_error_until_fallback_intrinsics_are_set(ros):
    node = start(ros)
    [status] = ros.answer(ros.publish(part_image()))
    assert status.level == DiagnosticStatus.ERROR and "no CameraInfo" in status.message
    assert "/camera_info" in status.message
    uncalibrated = camera_info_msg(CAMERA, ros.header())
    uncalibrated.k = [0.0] * 9
    ros.info_pub.publish(uncalibrated)
    wait_until(lambda: node.camera_info is not None, TIMEOUT, "the uncalibrated CameraInfo")
    [status] = ros.answer(ros.publish(part_image()))
    assert status.level == DiagnosticStatus.ERROR and "the last one was refused" in status.message
    node.set_parameters([Parameter("fx", value=210.0), Parameter("fy", value=210.0),
                         Parameter("cx", value=80.0), Parameter("cy", value=60.0)])
    ros.pose(ros.publish(part_image()))
    assert node.parts[0].estimator.calls[-1][1] == Camera(210.0, 210.0, 80.0, 60.0, 160, 120)


def test_camera_info_of_another_size_is_an_error(ros):
    start(ros)
    [status] = ros.answer(ros.publish(part_image((60, 80, 3)), CAMERA))
    assert status.level == DiagnosticStatus.ERROR and "160x120" in status.message


def test_estimator_exception_is_an_error_not_a_crash(ros):
    node = start(ros, factory=lambda graph, params: FakeEstimator(graph, params, fail=True))
    [status] = ros.answer(ros.publish(part_image(), CAMERA))
    assert status.level == DiagnosticStatus.ERROR and "boom" in status.message
    node.parts[0].estimator.fail = False
    ros.pose(ros.publish(part_image(), CAMERA))


def test_parameters_change_at_run_time_and_bad_values_are_refused(ros):
    node = start(ros)
    assert ros.answer(ros.publish(part_image(), CAMERA))[0].level == DiagnosticStatus.OK
    result = node.set_parameters([Parameter("pose.warn_error_ratio", value=0.1)])[0]
    assert result.successful
    [status] = ros.answer(ros.publish(part_image(), CAMERA))
    assert status.level == DiagnosticStatus.WARN and "error ratio 0.20 > pose.warn_error_ratio 0.1" in status.message
    assert node.parts[0].estimator.params.pose.warn_error_ratio == 0.1

    refused = node.set_parameters([Parameter("edges.blur_size", value=4)])[0]
    assert not refused.successful and "blur_size" in refused.reason
    assert not node.set_parameters([Parameter("fx", value=-1.0)])[0].successful
    assert not node.set_parameters([Parameter("graphs", value=["other.brepose.npz"])])[0].successful
    assert node.get_parameter("edges.blur_size").value == 5


def test_every_parameter_is_documented(ros):
    node = start(ros)
    descriptors = node.describe_parameters([n for n in node._parameters if n != "use_sim_time"])
    assert len(descriptors) > 40
    assert all(d.description for d in descriptors)
    assert node.describe_parameters(["matching.workers"])[0].type == ParameterType.PARAMETER_INTEGER


def test_debug_image_draws_the_matched_edges_while_subscribed(ros):
    node = start(ros)
    overlays = []
    ros.probe.create_subscription(Image, node.parts[0].debug_pub.topic_name, overlays.append, 10)
    wait_until(lambda: node.parts[0].debug_pub.get_subscription_count() > 0, TIMEOUT, "debug subscription")
    stamp = ros.publish(part_image((120, 160), np.uint16), CAMERA)
    overlay = wait_until(lambda: overlays, TIMEOUT, "a debug image")[0]
    assert overlay.encoding == "bgr8" and stamp_ns(overlay.header.stamp) == stamp
    pixels = image_from_msg(overlay)
    assert pixels.shape == (120, 160, 3)
    assert tuple(pixels[41, 80]) == FOUND_COLOUR, "the model edge at y=41 is drawn in green"


def test_several_parts_get_their_own_topics_and_statuses(ros):
    node = start(ros, graphs=["a.brepose.npz", "b.brepose.npz"], part_names=["left", "right"])
    assert [p.pose_pub.topic_name for p in node.parts] == ["/estimator/left/pose", "/estimator/right/pose"]
    stamp = ros.publish(part_image(), CAMERA)
    assert [s.name for s in ros.answer(stamp)] == ["estimator: left", "estimator: right"]
    ros.pose(stamp)


class OverlapEstimator(FakeEstimator):
    """A slow FakeEstimator that records when each call ran (perf_counter start, end)."""

    def __init__(self, graph, params):
        super().__init__(graph, params, delay=0.3)
        self.spans: list[tuple[float, float]] = []

    def estimate(self, image, camera, frame=None):
        start = time.perf_counter()
        try:
            return super().estimate(image, camera, frame)
        finally:
            self.spans.append((start, time.perf_counter()))


def test_two_parts_are_estimated_at_once_and_both_poses_published(ros):
    node = start(ros, factory=OverlapEstimator, graphs=["a.brepose.npz", "b.brepose.npz"],
                 part_names=["left", "right"])
    got = {name: [] for name in ("left", "right")}
    for part in node.parts:
        ros.probe.create_subscription(PoseStamped, part.pose_pub.topic_name, got[part.name].append, 10)
    stamp = ros.publish(part_image(), CAMERA)
    assert len(ros.answer(stamp)) == 2
    wait_until(lambda: all(got.values()), TIMEOUT, "both poses")
    assert {stamp_ns(msgs[0].header.stamp) for msgs in got.values()} == {stamp}
    (start_a, end_a), (start_b, end_b) = (part.estimator.spans[0] for part in node.parts)
    assert max(start_a, start_b) < min(end_a, end_b), "the two parts ran one after the other"
    # the image's edges were found once, by the first part for both, and both got them
    left, right = (part.estimator for part in node.parts)
    assert left.detected == [[right]] and right.detected == []
    assert left.frames == right.frames == [("frame", (120, 160, 3))]


def test_one_part_finds_its_own_edges(ros):
    node = start(ros)
    ros.answer(ros.publish(part_image(), CAMERA))
    assert node.parts[0].estimator.detected == [] and node.parts[0].estimator.frames == [None]


def test_only_the_newest_frame_is_processed(ros):
    node = start(ros, factory=lambda graph, params: FakeEstimator(graph, params, delay=0.3))
    stamps = []
    for _ in range(6):
        stamps.append(ros.publish(part_image(), CAMERA))
        time.sleep(0.03)
    [status] = ros.answer(stamps[-1])
    processed = len(node.parts[0].estimator.calls)
    assert processed <= 3, "frames queued up behind the slow estimator"
    assert len(ros.diagnostics.by_stamp) == processed
    assert "frames_skipped" in status_values(status)


@pytest.mark.parametrize("parameters, message", [
    ({"graphs": None}, "'graphs' is empty"),
    ({"graphs": ["bracket.step"], "part_names": ["bracket"]}, "refused: bracket.step is not an aspect graph"),
    ({"graphs": ["a.brepose.npz", "b.brepose.npz"], "part_names": ["a"]}, "one name per graph"),
    ({"graphs": ["a.brepose.npz"], "part_names": ["a/b"]}, "must start with a letter"),
    ({"graphs": ["a.brepose.npz"], "fx": 500}, "fx"),
    ({"graphs": ["a.brepose.npz"], "pose.confidence_file": "/nonexistent/c.yaml"},
     "calibration file /nonexistent/c.yaml does not exist"),
], ids=["no-graphs", "refused", "names", "topic", "type", "calibration"])
def test_startup_errors_are_clear(ros, parameters, message):
    with pytest.raises(StartupError, match=message):
        start(ros, **parameters)


def test_shipped_node_yaml_sets_only_declared_and_valid_parameters():
    check_params_file(CONFIG / "node.yaml")
    node_params = yaml.safe_load((CONFIG / "node.yaml").read_text())["estimator"]["ros__parameters"]
    groups = EstimatorParams().to_dict()
    EstimatorParams().with_flat({f"{g}.{k}": v for g in groups for k, v in node_params.get(g, {}).items()})


def test_main_refuses_an_unknown_parameter_in_the_params_file(tmp_path, capsys):
    params = tmp_path / "node.yaml"
    params.write_text("estimator:\n  ros__parameters:\n    graphs: [a.npz]\n"
                      "    matching:\n      empty_coeficient: 0.3\n")
    assert main(["estimator", "--params-file", str(params)]) == 2
    assert "unknown parameter(s): matching.empty_coeficient" in capsys.readouterr().err


@pytest.mark.parametrize("content, message", [
    (None, "does not exist"),
    (b"#!/bin/sh\necho not data\n", "not an aspect graph file"),
], ids=["missing", "not-a-graph"])
def test_graph_file_refused_by_the_loader_stops_the_start(ros, tmp_path, content, message):
    path = tmp_path / "bracket.brepose.npz"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(StartupError, match=f"aspect graph of part 'bracket' refused: .*{message}"):
        ros.start_node({"graphs": [str(path)]}, estimator_factory=FakeEstimator)


def test_a_parameter_change_waits_for_the_image_in_flight(ros):
    node = start(ros, factory=WatchedEstimator)
    estimator = node.parts[0].estimator
    stamp = ros.publish(part_image(), CAMERA)
    wait_until(lambda: estimator.busy, TIMEOUT, "the estimator at work")
    before = estimator.params.matching.workers
    after = before + 1
    assert node.set_parameters([Parameter("matching.workers", value=after)])[0].successful
    ros.answer(stamp)
    assert estimator.params.matching.workers == before, "the image in flight kept its parameters"
    ros.answer(ros.publish(part_image(), CAMERA))
    assert estimator.params.matching.workers == after and estimator.changed_while_busy == []


@pytest.mark.parametrize("name, value, reason", [
    ("matching.max_model_segments", 0, "range"),
    ("matching.rotation_candidates", 100000, "range"),
    ("pose.min_score", float("nan"), "range"),
    ("pose.min_score", 1.5, "range"),
    ("edges.blur_size", 4, "odd"),
    ("fx", -1.0, "range"),
    ("max_image_pixels", 0, "range"),
    ("image_transport", "compressed", "read-only"),
    ("pose.confidence_file", "/nonexistent/calibration.yaml", "calibration file"),
])
def test_out_of_range_values_are_refused_at_run_time_with_the_reason(ros, name, value, reason):
    node = start(ros)
    before = node.get_parameter(name).value
    result = node.set_parameters([Parameter(name, value=value)])[0]
    assert not result.successful and reason in result.reason.lower()
    assert node.get_parameter(name).value == before
    ros.pose(ros.publish(part_image(), CAMERA))


def test_descriptors_carry_the_ranges(ros):
    node = start(ros)
    [segments, score] = node.describe_parameters(["matching.max_model_segments", "pose.min_score"])
    assert (segments.integer_range[0].from_value, segments.integer_range[0].to_value) == (4, 200)
    assert (score.floating_point_range[0].from_value, score.floating_point_range[0].to_value) == (0.0, 1.0)


@pytest.mark.parametrize("parameters, message", [
    ({"matching.max_model_segments": 0}, "max_model_segments"),
    ({"pose.min_score": float("inf")}, "min_score"),
    ({"image_transport": "theora"}, "image_transport must be one of raw, compressed"),
], ids=["int-range", "inf", "transport"])
def test_out_of_range_start_values_stop_the_start(ros, parameters, message):
    with pytest.raises(StartupError, match=message):
        start(ros, **parameters)


def test_the_pose_with_covariance_comes_beside_the_pose(ros):
    node = start(ros)
    received = []
    ros.probe.create_subscription(PoseWithCovarianceStamped, node.parts[0].pose_covariance_pub.topic_name,
                                  received.append, 10)
    wait_until(lambda: node.parts[0].pose_covariance_pub.get_subscription_count() > 0, TIMEOUT, "subscription")
    stamp = ros.publish(part_image(), CAMERA)
    msg = wait_until(lambda: received, TIMEOUT, "a PoseWithCovarianceStamped")[0]
    assert stamp_ns(msg.header.stamp) == stamp and msg.header.frame_id == FRAME
    assert msg.pose.pose == ros.pose(stamp).pose


def test_compressed_transport_takes_png_and_jpeg(ros):
    node = start(ros, image_transport="compressed")
    assert node.image_input.topic == "/image_raw/compressed"
    publisher = ros.probe.create_publisher(CompressedImage, "image_raw/compressed", PUBLISHER_QOS["best_effort"])
    wait_until(lambda: publisher.get_subscription_count() > 0, TIMEOUT, "compressed subscription")
    for kind in ("png", "jpeg"):
        header = ros.header()
        ros.info_pub.publish(camera_info_msg(CAMERA, header))
        publisher.publish(compressed_image_msg(part_image(), header, kind))
        ros.pose(stamp_ns(header.stamp))
    assert [call[0] for call in node.parts[0].estimator.calls] == [(120, 160, 3)] * 2


def test_rectified_input_uses_p_and_no_distortion(ros):
    node = start(ros, input_is_rectified=True)
    info = camera_info_msg(Camera(200.0, 200.0, 79.5, 59.5, 160, 120, (0.1, 0.0, 0.0, 0.0, 0.0)), ros.header())
    info.p = [190.0, 0.0, 81.0, 0.0, 0.0, 191.0, 58.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    header = ros.header()
    info.header = header
    ros.info_pub.publish(info)
    ros.image_pub.publish(image_msg(part_image(), header))
    ros.pose(stamp_ns(header.stamp))
    assert node.parts[0].estimator.calls[-1][1] == Camera(190.0, 191.0, 81.0, 58.0, 160, 120)
    assert node.set_parameters([Parameter("input_is_rectified", value=False)])[0].successful
    stamp = ros.publish(part_image())
    ros.pose(stamp)
    assert node.parts[0].estimator.calls[-1][1].distortion == (0.1, 0.0, 0.0, 0.0, 0.0)


def test_qos_override_in_the_parameter_file_fixes_the_reliability(ros):
    node = start(ros, **{"qos_overrides./image_raw.subscription.reliability": "reliable"})
    assert not node.image_input.follows_publishers
    assert node.image_input.reliability == ReliabilityPolicy.RELIABLE
    reliable = ros.probe.create_publisher(Image, "image_raw", PUBLISHER_QOS["reliable"])
    wait_until(lambda: reliable.get_subscription_count() > 0, TIMEOUT, "reliable match")


def test_the_subscription_follows_a_reliable_publisher(ros):
    node = start(ros)
    assert node.image_input.reliability == ReliabilityPolicy.BEST_EFFORT  # the probe is best effort
    ros.probe.destroy_publisher(ros.image_pub)
    reliable = ros.probe.create_publisher(Image, "image_raw", PUBLISHER_QOS["reliable"])
    wait_until(lambda: node.image_input.reliability == ReliabilityPolicy.RELIABLE, TIMEOUT, "a reliable subscription")
    wait_until(lambda: reliable.get_subscription_count() > 0, TIMEOUT, "reliable match")
    header = ros.header()
    ros.info_pub.publish(camera_info_msg(CAMERA, header))
    reliable.publish(image_msg(part_image(), header))
    ros.pose(stamp_ns(header.stamp))


def test_heartbeat_while_no_image_arrives(ros):
    start(ros)
    beat = wait_until(lambda: [a for a in ros.diagnostics.by_stamp.values()
                               if a.status[0].name == "estimator: input"], 3 * TIMEOUT, "a heartbeat")[0]
    [status] = beat.status
    assert status.level == DiagnosticStatus.WARN and "no image received on /image_raw yet" in status.message
    assert status_values(status)["publishers"] == "1"
    ros.pose(ros.publish(part_image(), CAMERA))
    assert float(status_values(ros.answer(ros.publish(part_image(), CAMERA))[0])["input_hz"]) > 0


def test_real_pipeline_covariance_is_a_small_positive_definite_matrix(ros, sample):
    node = start_real(ros, sample)
    received = []
    ros.probe.create_subscription(PoseWithCovarianceStamped, node.parts[0].pose_covariance_pub.topic_name,
                                  received.append, 10)
    wait_until(lambda: node.parts[0].pose_covariance_pub.get_subscription_count() > 0, TIMEOUT, "subscription")
    ros.publish(sample.image, sample.camera)
    covariance = np.reshape(wait_until(lambda: received, 3 * TIMEOUT, "a pose with covariance")[0].pose.covariance,
                            (6, 6))
    assert np.all(np.linalg.eigvalsh(covariance) > 0)
    position_sigma = np.sqrt(np.diag(covariance)[:3])
    assert np.all(position_sigma < 0.05 * sample.diameter), position_sigma
    assert np.all(np.degrees(np.sqrt(np.diag(covariance)[3:])) < 5.0)


def test_diagnostics_say_when_the_best_pose_lies_outside_the_working_range():
    from brepose_ros.ros.node import diagnose

    params = EstimatorParams().with_flat({"pose.min_distance": 0.4, "pose.max_distance": 0.6})
    far = Estimate(False, None, None, score=0.8, error_ratio=0.2, view_index=3, n_image_segments=12, n_matched=8,
                   n_nearest=6, confidence=0.7, distance=0.95)
    level, message = diagnose(far, params)
    assert level == DiagnosticStatus.WARN
    assert "0.95 m away" in message and "pose.min_distance 0.4 - pose.max_distance 0.6" in message
    inside = Estimate(False, None, None, score=0.3, error_ratio=0.2, view_index=3, n_image_segments=12, n_matched=8,
                      n_nearest=6, confidence=0.01, distance=0.5)
    assert "pose.min_score" in diagnose(inside, params)[1]


def test_diagnostics_name_the_steps_a_time_budget_left_out():
    from brepose_ros.ros.node import estimate_values

    hurried = Estimate(True, R_FAKE, T_FAKE, score=0.8, error_ratio=0.2, view_index=3, n_image_segments=12,
                       n_matched=8, n_nearest=6, skipped=("seeded", "small", "larger"))
    assert estimate_values(hurried)["skipped"] == "seeded small larger"
    assert estimate_values(replace(hurried, skipped=()))["skipped"] == ""


def test_diagnostics_carry_the_shading_fit_where_it_was_measured():
    from brepose_ros.ros.node import estimate_values

    checked = Estimate(True, R_FAKE, T_FAKE, score=0.8, error_ratio=0.2, view_index=3, n_image_segments=12,
                       n_matched=8, n_nearest=6, shading_fit=0.93)
    assert estimate_values(checked)["shading_fit"] == pytest.approx(0.93)
    assert estimate_values(replace(checked, shading_fit=None))["shading_fit"] == -1.0

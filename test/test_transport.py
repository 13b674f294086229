"""The node in its own process, fed bgr8 frames by play_bag.py from another, as a camera
driver would (../shared/ROS2_ON_PIP.md: large frames are lost only between processes).

Every frame must be answered in lock-step from a reliable publisher, and from a best-effort
one under config/fastdds_large_images.xml (docs/ros.md); a best-effort publisher under Fast
DDS defaults loses most 640x480 frames, and the node must say so. Frames are uniform grey:
the estimator answers them at once (no edges), so the test measures the transport.
"""
from __future__ import annotations

import random
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from brepose_ros.camera import Camera
from brepose_ros.ros.bags import write_bag
from node_helpers import ros_env

REPO = Path(__file__).resolve().parents[1]
LARGE_IMAGES_XML = REPO / "config" / "fastdds_large_images.xml"
PLAY_BAG = REPO / "launch_free_scripts" / "play_bag.py"
SIZES = {"640x480": (640, 480, 30), "1920x1080": (1920, 1080, 10)}  # width, height, frames
TIMEOUT = 30.0
#: a node's start: importing rclpy and numba and loading the compiled kernels is 1-3 s of CPU,
#: but on 2 cores shared with other test runs it took over 30 s of wall time
START_TIMEOUT = 120.0

pytestmark = [pytest.mark.ros, pytest.mark.slow]


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    folder = tmp_path_factory.mktemp("transport")
    out = {}
    for name, (width, height, count) in SIZES.items():
        camera = Camera.from_fov(width, height, float(width))
        frames = (np.full((height, width, 3), 100, np.uint8) for _ in range(count))
        write_bag(folder / name, frames, camera, rate=30.0)
        out[name] = folder / name
    return out


class NodeProcess:
    def __init__(self, graph: Path, folder: Path, env: dict):
        params = folder / "node.yaml"
        params.write_text(f"estimator:\n  ros__parameters:\n    graphs: [{graph}]\n    debug_image: false\n")
        self.log = folder / "node.log"
        self.env = env
        self.process = subprocess.Popen([sys.executable, "-m", "brepose_ros.ros.node", "--params-file", str(params),
                                         "--ros-args", "-r", "image_raw:=/camera/image_raw",
                                         "-r", "camera_info:=/camera/camera_info"],
                                        stdout=self.log.open("w"), stderr=subprocess.STDOUT, env=env, cwd=folder)
        deadline = time.monotonic() + START_TIMEOUT
        while "estimating" not in self.log.read_text():
            assert self.process.poll() is None and time.monotonic() < deadline, self.log.read_text()
            time.sleep(0.1)

    def play(self, bag: Path, *options: str) -> int:
        """Frames answered of a lock-step play_bag.py run."""
        result = subprocess.run([sys.executable, str(PLAY_BAG), str(bag), "--image-topic", "/camera/image_raw",
                                 "--info-topic", "/camera/camera_info", "--timeout", "10", *options],
                                capture_output=True, text=True, env=self.env, timeout=180)
        assert result.returncode == 0, result.stderr
        return int(re.search(r"the node answered (\d+)", result.stdout).group(1))

    def close(self) -> None:
        self.process.terminate()
        self.process.wait(timeout=TIMEOUT)


@pytest.fixture(scope="module")
def graph(sample_step, tmp_path_factory):
    from brepose_ros.offline.compiler import compile_aspect_graph
    path = tmp_path_factory.mktemp("transport_graph") / "sample_bracket.brepose.npz"
    return compile_aspect_graph(sample_step, step_deg=30.0, workers=1, progress=False).save(path)


@pytest.fixture(scope="module", params=["fastdds-defaults", "large-images-xml"])
def node(request, graph, tmp_path_factory):
    extra = {"FASTDDS_DEFAULT_PROFILES_FILE": str(LARGE_IMAGES_XML)} if request.param == "large-images-xml" else {}
    process = NodeProcess(graph, tmp_path_factory.mktemp(request.param),
                          ros_env(ROS_DOMAIN_ID=str(random.randint(100, 200)), **extra))
    process.setting = request.param
    yield process
    process.close()


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("reliability", ["reliable", "best_effort"])
def test_every_frame_is_answered_from_another_process(node, bags, size, reliability):
    if reliability == "best_effort" and node.setting == "fastdds-defaults":
        pytest.skip("Fast DDS defaults lose large best-effort frames: see the test below")
    answered = node.play(bags[size], "--reliability", reliability)
    assert answered == SIZES[size][2], f"{answered} of {SIZES[size][2]} {size} frames answered"


def test_lost_best_effort_frames_are_reported(node, bags):
    if node.setting != "fastdds-defaults":
        pytest.skip("only Fast DDS defaults lose frames")
    answered = node.play(bags["640x480"], "--reliability", "best_effort", "--mode", "rate")
    assert answered < SIZES["640x480"][2], "Fast DDS defaults delivered every large best-effort frame"
    deadline = time.monotonic() + 5.0
    while "frames lost on /camera/image_raw" not in node.log.read_text():
        assert time.monotonic() < deadline, f"no loss reported; node log:\n{node.log.read_text()}"
        time.sleep(0.1)

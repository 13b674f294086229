"""launch_free_scripts/run_partitioned.py: two estimator processes, one part each, answer
the same images published from a third process (play_bag.py), each with its own status."""
from __future__ import annotations

import importlib.util
import random
import re
import shutil
import signal
import subprocess
import sys
import time

import pytest

from brepose_ros.ros.bags import write_bag
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene
from node_helpers import ros_env
from test_transport import PLAY_BAG, REPO, START_TIMEOUT, TIMEOUT

RUN_PARTITIONED = REPO / "launch_free_scripts" / "run_partitioned.py"


def partition(*args):
    spec = importlib.util.spec_from_file_location("run_partitioned", RUN_PARTITIONED)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.partition(*args)


def test_partition_deals_the_parts_round_robin():
    assert partition(["a", "b", "c"], ["A", "B", "C"], 2) == [(["a", "c"], ["A", "C"]), (["b"], ["B"])]
    assert partition(["a"], ["A"], 3) == [(["a"], ["A"])]


@pytest.mark.ros
@pytest.mark.slow
def test_two_processes_each_answer_their_part(sample_step, tmp_path):
    from brepose_ros.offline.compiler import compile_aspect_graph
    import cv2

    graph = compile_aspect_graph(sample_step, step_deg=30.0, workers=1, progress=False).save(
        tmp_path / "left.brepose.npz")
    shutil.copy(graph, tmp_path / "right.brepose.npz")
    scene = generate_scene(sample_step, tmp_path / "scene", 2, seed=1, config=SceneConfig(width=320, height=240,
                                                                                         fx=300.0))
    frames = (cv2.imread(str(e.path), cv2.IMREAD_UNCHANGED) for e in scene.entries)
    write_bag(tmp_path / "bag", frames, scene.camera, rate=10.0)
    env = ros_env(ROS_DOMAIN_ID=str(random.randint(100, 200)))
    log = tmp_path / "partitioned.log"
    remaps = ["-r", "image_raw:=/camera/image_raw", "-r", "camera_info:=/camera/camera_info"]
    process = subprocess.Popen([sys.executable, str(RUN_PARTITIONED), "--processes", "2", "--graphs",
                                str(tmp_path / "left.brepose.npz"), str(tmp_path / "right.brepose.npz"), "--",
                                *remaps], stdout=log.open("w"), stderr=subprocess.STDOUT, env=env, cwd=tmp_path)
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while log.read_text().count("estimating") < 2:
            assert process.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.1)
        result = subprocess.run([sys.executable, str(PLAY_BAG), str(tmp_path / "bag"), "--image-topic",
                                 "/camera/image_raw", "--info-topic", "/camera/camera_info", "--reliability",
                                 "reliable", "--nodes", "2", "--statuses", "2", "--timeout", "20"],
                                capture_output=True, text=True, env=env, timeout=180)
        assert result.returncode == 0, result.stderr
        assert int(re.search(r"the node answered (\d+)", result.stdout).group(1)) == 2, result.stdout
        assert "answered by: estimator_0: left, estimator_1: right" in result.stdout
    finally:
        process.send_signal(signal.SIGINT)
        assert process.wait(timeout=TIMEOUT) == 0, log.read_text()

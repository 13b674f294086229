"""A robot install: ``pip install '.[ros]'`` in a fresh virtualenv (no system site packages,
no cadquery, no VTK, no matplotlib) gives a node that loads a precompiled aspect graph and
answers an image, and a brepose-compile that says what it lacks. Slow (a real pip install
from the package index, 2-3 minutes): ``pytest -m 'not slow'`` leaves it out.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from brepose_ros.offline.compiler import compile_aspect_graph
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene

REPO = Path(__file__).resolve().parents[1]
#: what ``pip install .`` reads; copied so the build leaves nothing in the work tree
SOURCES = ("setup.py", "setup.cfg", "package.xml", "resource", "config", "brepose_ros")
CAD_STACK = ("cadquery", "OCP", "vtk", "matplotlib")

ANSWER_ONE_IMAGE = """
import os, sys
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "OFF"
from rclpy.parameter import Parameter
from std_msgs.msg import Header
from brepose_ros.camera import Camera
from brepose_ros.image_codec import read_image_file
from brepose_ros.ros.messages import camera_info_msg, image_msg, stamp_from_ns
from brepose_ros.ros.node import EstimatorNode
from brepose_ros.ros.replay import Player, PoseRecorder, RosSession

graph, image, camera = sys.argv[1], read_image_file(sys.argv[2]), Camera.load(sys.argv[3])
with RosSession() as ros:
    node = ros.add(EstimatorNode(context=ros.context, parameter_overrides=[Parameter("graphs", value=[graph])]))
    client = ros.node("robot_probe")
    player = Player(client)
    recorder = PoseRecorder(client, node.parts[0].pose_pub.topic_name, diagnostics=player.diagnostics)
    player.wait_for_node()
    header = Header(stamp=stamp_from_ns(10**9), frame_id="camera")
    player.play([(10**9, image_msg(image, header), camera_info_msg(camera, header))], timeout=60.0)
    [prediction] = recorder.predictions()
print("found" if prediction["R"] is not None else "not found", prediction["score"])
print("loaded:", [m for m in sys.modules if m.split(".")[0] in %r])
""" % (CAD_STACK,)


def clean_env() -> dict:
    """This process's environment without what points at the test venv or this work tree."""
    return {k: v for k, v in os.environ.items()
            if k not in ("_ROS_WHEELS_BOOTSTRAP_COMPLETE", "LD_LIBRARY_PATH", "PYTHONPATH", "VIRTUAL_ENV")}


@pytest.mark.slow
@pytest.mark.ros
def test_ros_extra_alone_runs_the_node_without_the_cad_stack(sample_step, tmp_path):
    graph = compile_aspect_graph(sample_step, step_deg=20.0, workers=1, progress=False).save(
        tmp_path / "sample_bracket.brepose.npz")
    scene = generate_scene(sample_step, tmp_path / "scene", 1, seed=1,
                           config=SceneConfig(width=320, height=240, fx=300.0))
    source = tmp_path / "source"
    source.mkdir()
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, source / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(REPO / name, source / name)
    venv = tmp_path / "robot"
    env = clean_env()
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, env=env)
    python = venv / "bin" / "python"
    install = subprocess.run([str(python), "-m", "pip", "install", "--quiet", f"{source}[ros]"],
                             capture_output=True, text=True, env=env, timeout=1200)
    assert install.returncode == 0, install.stderr[-3000:]

    for module in CAD_STACK:
        found = subprocess.run([str(python), "-c", f"import importlib.util as u; print(u.find_spec({module!r}))"],
                               capture_output=True, text=True, env=env, cwd=tmp_path)
        assert found.stdout.strip() == "None", f"{module} is installed by the [ros] extra"

    script = tmp_path / "answer.py"
    script.write_text(textwrap.dedent(ANSWER_ONE_IMAGE))
    run = subprocess.run([str(python), str(script), str(graph), str(scene.entries[0].path),
                          str(scene.folder / "camera.json")], capture_output=True, text=True, env=env,
                         cwd=tmp_path, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    # the node answered with a score; found or not is the estimator's business: on this
    # 320 x 240 image with a 20-degree graph its pose is 25 degrees off, which the former
    # score reported as found (0.695) and the a-contrario score does not (0.48)
    verdict, score = run.stdout.splitlines()[0].rsplit(" ", 1)
    assert verdict in ("found", "not found") and 0.0 < float(score) <= 1.0, run.stdout
    assert "loaded: []" in run.stdout

    compile_cli = subprocess.run([str(venv / "bin" / "brepose-compile"), str(sample_step)],
                                 capture_output=True, text=True, env=env, cwd=tmp_path)
    assert compile_cli.returncode == 2
    assert compile_cli.stderr.strip().splitlines() == [
        "error: this command needs the CAD stack (OCP is not installed): pip install 'brepose_ros[compile]'"]

"""The bad-input corpus: every entry point refuses every kind of broken input clearly.

Commands (brepose-compile, -estimate, -bag, -render, -eval, the estimator node's main and
play_bag.py) must exit with status 2 and one line on stderr naming the problem, never a
traceback. The running node must answer a bad image, CameraInfo or parameter with an ERROR
(or a refused change with its reason), keep answering good images and keep its memory
bounded. Each case is one kind of damage; ``KINDS`` counts them.
"""
from __future__ import annotations

import importlib.util
import json
import math
import os
import struct
import zipfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticStatus
from rclpy.parameter import Parameter
from rosbags.typesys import Stores, get_typestore
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header

from brepose_ros import aspect_graph
from brepose_ros.camera import Camera
from brepose_ros.cli import bag as bag_cli
from brepose_ros.cli import compile as compile_cli
from brepose_ros.cli import estimate as estimate_cli
from brepose_ros.cli import evaluate as evaluate_cli
from brepose_ros.cli import render as render_cli
from brepose_ros.offline.compiler import compile_aspect_graph
from brepose_ros.ros import node as node_main
from brepose_ros.ros.bags import write_bag
from brepose_ros.ros.messages import PUBLISHER_QOS, camera_info_msg
from brepose_ros.ros.replay import wait_until
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene
from node_helpers import TIMEOUT, Harness
from test_bags import write_foreign_bag

REPO = Path(__file__).resolve().parents[1]
STORE = get_typestore(Stores.ROS2_KILTED)


def load_script(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "launch_free_scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


play_bag = load_script("play_bag")


# -- the inputs ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def good(sample_step, tmp_path_factory):
    """A valid graph, scene, image, camera and params file, from which the bad ones are made."""
    folder = tmp_path_factory.mktemp("corpus")
    graph = compile_aspect_graph(sample_step, step_deg=30.0, workers=1, progress=False).save(
        folder / "sample_bracket.brepose.npz")
    scene = generate_scene(sample_step, folder / "scene", 1, seed=3,
                           config=SceneConfig(width=160, height=120, fx=150.0))
    return {"folder": folder, "step": sample_step, "graph": graph, "scene": scene.folder,
            "image": scene.entries[0].path, "camera": scene.folder / "camera.json"}


def write(folder: Path, name: str, content: bytes | str) -> Path:
    path = folder / name
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    return path


def png_claiming(width: int, height: int) -> bytes:
    """A PNG signature and IHDR claiming a size, followed by a tiny deflate stream: what a
    decompression bomb looks like to a reader that trusts the header."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(bytes(4096)))
            + chunk(b"IEND", b""))


def jpeg_claiming(width: int, height: int) -> bytes:
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 11, 8, height, width, 1) + b"\x01\x11\x00"
    return b"\xff\xd8" + sof + b"\xff\xda\x00\x08\x01\x01\x00\x00\x3f\x00" + bytes(64) + b"\xff\xd9"


def rewrite_graph(good_path: Path, out: Path, change) -> Path:
    """A copy of a graph with ``change(metadata, arrays)`` applied and a fresh digest: a file a
    broken compiler (or someone who knows the format) could write."""
    with np.load(good_path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files if name != "metadata"}
        metadata = json.loads(str(npz["metadata"]))
    metadata.pop("content_sha256")
    change(metadata, arrays)
    metadata["content_sha256"] = aspect_graph._digest(metadata, {k: arrays[k] for k in aspect_graph._ARRAYS})
    np.savez_compressed(out, metadata=np.array(json.dumps(metadata, sort_keys=True)), **arrays)
    return out


def zip_claiming_inflated(good_path: Path, out: Path, size: int) -> Path:
    """The graph with one central-directory entry claiming ``size`` inflated bytes."""
    data = bytearray(good_path.read_bytes())
    at = data.rfind(b"PK\x01\x02")  # the last central directory header
    data[at + 24:at + 28] = struct.pack("<I", size)
    out.write_bytes(bytes(data))
    return out


def npy_claiming_shape(good_path: Path, out: Path) -> Path:
    """An npz whose seg_3d .npy header claims 10^9 elements it does not hold."""
    with zipfile.ZipFile(good_path) as source, zipfile.ZipFile(out, "w") as target:
        for info in source.infolist():
            data = source.read(info)
            if info.filename == "seg_3d.npy":
                header = "{'descr': '<f8', 'fortran_order': False, 'shape': (1000000000, 2, 3), }"
                header = header.ljust(117) + "\n"
                data = b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode() + data[128:]
            target.writestr(info.filename, data)
    return out


def step_without_solids() -> str:
    return ("ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION((''),'2;1');\nFILE_NAME('','',(''),(''),'','','');\n"
            "FILE_SCHEMA(('AUTOMOTIVE_DESIGN'));\nENDSEC;\nDATA;\n"
            "#1=CARTESIAN_POINT('',(0.,0.,0.));\nENDSEC;\nEND-ISO-10303-21;\n")


def foreign_bag(path: Path, messages) -> Path:
    write_foreign_bag(path, messages)
    return path


def bag_header(sec: int = 1):
    types = STORE.types
    return types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=0), frame_id="c")


def bag_image(encoding="mono8", width=8, height=8, step=8, size=64):
    return ("/cam/image_raw", "sensor_msgs/msg/Image", STORE.types["sensor_msgs/msg/Image"](
        header=bag_header(), height=height, width=width, encoding=encoding, is_bigendian=0, step=step,
        data=np.zeros(size, np.uint8)))


def bag_compressed(data: bytes, fmt="png"):
    return ("/cam/image_raw/compressed", "sensor_msgs/msg/CompressedImage",
            STORE.types["sensor_msgs/msg/CompressedImage"](header=bag_header(), format=fmt,
                                                           data=np.frombuffer(data, np.uint8)))


def bag_camera_info(k):
    types = STORE.types
    return ("/cam/camera_info", "sensor_msgs/msg/CameraInfo", types["sensor_msgs/msg/CameraInfo"](
        header=bag_header(), height=8, width=8, distortion_model="plumb_bob", d=np.zeros(5), k=np.array(k, float),
        r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0, binning_y=0,
        roi=types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)))


# -- the commands -------------------------------------------------------------------------

def estimate_args(g, tmp, graph=None, camera=None, image=None, params=None):
    args = [str(image or g["image"]), "--graph", str(graph or g["graph"]), "--camera", str(camera or g["camera"]),
            "-o", str(tmp / "predictions.json")]
    return args + (["--params", str(params)] if params else [])


def node_file(tmp, text: str) -> Path:
    return write(tmp, "node.yaml", text)


def graphs_yaml(g, extra: str = "") -> str:
    return f"estimator:\n  ros__parameters:\n    graphs: [{g['graph']}]\n{extra}"


K_GOOD = [8.0, 0, 4, 0, 8.0, 4, 0, 0, 1]

#: (id, command, argv builder (good inputs, tmp folder) -> argv, expected words in the message)
COMMAND_CASES = [
    # STEP files
    ("step-missing", compile_cli, lambda g, t: [str(t / "none.step")], "does not exist"),
    ("step-empty", compile_cli, lambda g, t: [str(write(t, "e.step", ""))], "empty"),
    ("step-text", compile_cli, lambda g, t: [str(write(t, "t.step", "hello\n"))], "not a STEP file"),
    ("step-binary", compile_cli, lambda g, t: [str(write(t, "b.step", os.urandom(2048)))], "not a STEP file"),
    ("step-truncated", compile_cli,
     lambda g, t: [str(write(t, "h.step", g["step"].read_bytes()[: g["step"].stat().st_size // 2]))], "truncated"),
    ("step-no-solid", compile_cli, lambda g, t: [str(write(t, "n.step", step_without_solids()))], "no"),
    ("step-directory", compile_cli, lambda g, t: [str(t)], "does not exist"),
    ("step-oversized", compile_cli,
     lambda g, t: [str(write(t, "big.step", b"ISO-10303-21;" + bytes(65 * 2**20)))], "over the limit"),
    # meshes: a unit is required, and a mesh without triangles is refused (test_mesh.py has the rest)
    ("mesh-no-units", compile_cli, lambda g, t: [str(write(t, "u.stl", "solid p\nendsolid p\n"))],
     "give its length unit with --units"),
    ("mesh-stl", compile_cli, lambda g, t: [str(write(t, "p.stl", "solid p\nendsolid p\n")), "--units", "mm"],
     "holds no triangles"),
    ("mesh-ply", compile_cli,
     lambda g, t: [str(write(t, "p.ply", "ply\nformat ascii 1.0\nend_header\n")), "--units", "mm"],
     "holds no triangles"),
    ("mesh-obj", compile_cli, lambda g, t: [str(write(t, "p.obj", "v 0 0 0\n")), "--units", "mm"],
     "holds no triangles"),
    # compile flags
    ("flag-step-deg-zero", compile_cli, lambda g, t: [str(g["step"]), "--step-deg", "0"], "positive"),
    ("flag-step-deg-nan", compile_cli, lambda g, t: [str(g["step"]), "--step-deg", "nan"], "positive"),
    ("flag-step-deg-fine", compile_cli, lambda g, t: [str(g["step"]), "--step-deg", "0.01"], "[1, 90]"),
    ("flag-step-deg-text", compile_cli, lambda g, t: [str(g["step"]), "--step-deg", "five"], "not a number"),
    ("flag-lonlat-one", compile_cli, lambda g, t: [str(g["step"]), "--lonlat", "1"], "[2, 200]"),
    ("flag-lonlat-huge", compile_cli, lambda g, t: [str(g["step"]), "--lonlat", "100000"], "[2, 200]"),
    ("flag-workers-zero", compile_cli, lambda g, t: [str(g["step"]), "--workers", "0"], "positive integer"),
    ("flag-chord-zero", compile_cli, lambda g, t: [str(g["step"]), "--chord-tolerance", "0"], "positive"),
    ("flag-min-length-negative", compile_cli, lambda g, t: [str(g["step"]), "--min-length", "-1"], ">= 0"),
    ("flag-method", compile_cli, lambda g, t: [str(g["step"]), "--method", "fancy"], "invalid choice"),
    ("flag-both-view-kinds", compile_cli, lambda g, t: [str(g["step"]), "--step-deg", "5", "--lonlat", "4"],
     "not allowed"),
    ("flag-unknown", compile_cli, lambda g, t: [str(g["step"]), "--bogus"], "unrecognized"),
    # aspect graphs
    ("graph-missing", estimate_cli, lambda g, t: estimate_args(g, t, graph=t / "none.brepose.npz"), "does not exist"),
    ("graph-empty", estimate_cli, lambda g, t: estimate_args(g, t, graph=write(t, "e.brepose.npz", "")),
     "not an aspect graph"),
    ("graph-text", estimate_cli, lambda g, t: estimate_args(g, t, graph=write(t, "t.brepose.npz", "#!/bin/sh\n")),
     "not an aspect graph"),
    ("graph-truncated", estimate_cli, lambda g, t: estimate_args(g, t, graph=write(
        t, "h.brepose.npz", g["graph"].read_bytes()[: g["graph"].stat().st_size // 2])), "truncated"),
    ("graph-plain-zip", estimate_cli, lambda g, t: estimate_args(g, t, graph=plain_zip(t)), "not an aspect graph"),
    ("graph-bit-flip", estimate_cli, lambda g, t: estimate_args(g, t, graph=flipped(g, t)), "modified"),
    ("graph-newer-version", estimate_cli, lambda g, t: estimate_args(g, t, graph=rewrite_graph(
        g["graph"], t / "v.brepose.npz", lambda m, a: m.update(format_version=99))), "newer"),
    ("graph-nan", estimate_cli, lambda g, t: estimate_args(g, t, graph=rewrite_graph(
        g["graph"], t / "nan.brepose.npz", lambda m, a: a["seg_3d"].__setitem__((0, 0, 0), np.nan))),
     "NaN or infinite"),
    ("graph-bad-diameter", estimate_cli, lambda g, t: estimate_args(g, t, graph=rewrite_graph(
        g["graph"], t / "d.brepose.npz", lambda m, a: m.update(model_diameter=-1.0))), "model_diameter"),
    ("graph-zip-bomb", estimate_cli, lambda g, t: estimate_args(g, t, graph=zip_claiming_inflated(
        g["graph"], t / "bomb.brepose.npz", 3 * 2**30)), "inflate"),
    ("graph-npy-header-lies", estimate_cli, lambda g, t: estimate_args(g, t, graph=npy_claiming_shape(
        g["graph"], t / "lie.brepose.npz")), "claims shape"),
    # images
    ("image-missing", estimate_cli, lambda g, t: estimate_args(g, t, image=t / "none.png"), "cannot read image"),
    ("image-text", estimate_cli, lambda g, t: estimate_args(g, t, image=write(t, "t.png", "not an image")),
     "cannot read image"),
    ("image-empty", estimate_cli, lambda g, t: estimate_args(g, t, image=write(t, "e.png", "")), "cannot read image"),
    ("image-png-bomb", estimate_cli, lambda g, t: estimate_args(g, t, image=write(
        t, "bomb.png", png_claiming(100_000, 100_000))), "exceeds the limit"),
    ("image-jpeg-bomb", estimate_cli, lambda g, t: estimate_args(g, t, image=write(
        t, "bomb.jpg", jpeg_claiming(60_000, 60_000))), "exceeds the limit"),
    ("image-png-truncated", estimate_cli, lambda g, t: estimate_args(g, t, image=write(
        t, "cut.png", g["image"].read_bytes()[:100])), "does not decode"),
    ("image-jpeg-truncated", estimate_cli, lambda g, t: estimate_args(g, t, image=write(
        t, "cut.jpg", cv2.imencode(".jpg", cv2.imread(str(g["image"])))[1].tobytes()[:300])), "does not decode"),
    ("image-wrong-size", estimate_cli, lambda g, t: estimate_args(g, t, image=write(
        t, "small.png", cv2.imencode(".png", np.zeros((60, 80), np.uint8))[1].tobytes())), "does not fit"),
    # camera.json
    ("camera-missing", estimate_cli, lambda g, t: estimate_args(g, t, camera=t / "none.json"), "does not exist"),
    ("camera-not-json", estimate_cli, lambda g, t: estimate_args(g, t, camera=write(t, "c.json", "{fx: 1")),
     "not valid JSON"),
    ("camera-array", estimate_cli, lambda g, t: estimate_args(g, t, camera=write(t, "c.json", "[1, 2]")),
     "JSON object"),
    ("camera-lacks-fx", estimate_cli, lambda g, t: estimate_args(g, t, camera=camera_file(t, fx=None)), "lacks fx"),
    ("camera-negative-fx", estimate_cli, lambda g, t: estimate_args(g, t, camera=camera_file(t, fx=-150.0)),
     "positive"),
    ("camera-nan-fx", estimate_cli, lambda g, t: estimate_args(g, t, camera=camera_file(t, fx=math.nan)), "finite"),
    ("camera-text-fx", estimate_cli, lambda g, t: estimate_args(g, t, camera=camera_file(t, fx="wide")),
     "non-numeric"),
    ("camera-distortion-3", estimate_cli, lambda g, t: estimate_args(g, t, camera=camera_file(
        t, distortion=[0.1, 0.0, 0.0])), "coefficients"),
    ("camera-zero-width", estimate_cli, lambda g, t: estimate_args(g, t, camera=camera_file(t, width=0)),
     "size must be positive"),
    # estimator parameter files of the commands
    ("params-missing", estimate_cli, lambda g, t: estimate_args(g, t, params=t / "none.yaml"), "does not exist"),
    ("params-bad-yaml", estimate_cli, lambda g, t: estimate_args(g, t, params=write(t, "p.yaml", "pose: [x\n")),
     "not valid YAML"),
    ("params-list", estimate_cli, lambda g, t: estimate_args(g, t, params=write(t, "p.yaml", "- 1\n- 2\n")),
     "mapping"),
    ("params-unknown-group", estimate_cli, lambda g, t: estimate_args(g, t, params=write(t, "p.yaml", "posе: {}\n")),
     "unknown parameter group"),
    ("params-typo", estimate_cli, lambda g, t: estimate_args(g, t, params=write(
        t, "p.yaml", "matching:\n  empty_coeficient: 0.3\n")), "empty_coeficient"),
    ("params-wrong-type", estimate_cli, lambda g, t: estimate_args(g, t, params=write(
        t, "p.yaml", "pose:\n  refine_iterations: many\n")), "must be int"),
    ("params-out-of-range", estimate_cli, lambda g, t: estimate_args(g, t, params=write(
        t, "p.yaml", "matching:\n  max_model_segments: 0\n")), "[4, 200]"),
    ("params-nan", estimate_cli, lambda g, t: estimate_args(g, t, params=write(
        t, "p.yaml", "pose:\n  min_score: .nan\n")), "[0, 1]"),
    ("params-binary", estimate_cli, lambda g, t: estimate_args(g, t, params=write(t, "p.yaml", b"\xff\xfe\x00")),
     "parameter file"),
    # the estimator node's start
    ("node-params-missing", node_main, lambda g, t: ["estimator", "--params-file", str(t / "none.yaml")],
     "No such file"),
    ("node-params-bad-yaml", node_main, lambda g, t: ["estimator", "--params-file", str(node_file(t, "a: [\n"))],
     "not valid YAML"),
    ("node-params-list", node_main, lambda g, t: ["estimator", "--params-file", str(node_file(t, "- a\n"))],
     "must map node names"),
    ("node-params-typo", node_main, lambda g, t: ["estimator", "--params-file", str(node_file(
        t, graphs_yaml(g, "    pose:\n      min_scor: 0.5\n")))], "pose.min_scor"),
    ("node-ros-args-typo", node_main, lambda g, t: ["estimator", "--ros-args", "--params-file", str(node_file(
        t, graphs_yaml(g, "    matching:\n      worker: 2\n")))], "matching.worker"),
    ("node-graph-missing", node_main, lambda g, t: ["estimator", "--params-file", str(node_file(
        t, "estimator:\n  ros__parameters:\n    graphs: [none.brepose.npz]\n"))], "does not exist"),
    ("node-no-graphs", node_main, lambda g, t: ["estimator", "--params-file", str(node_file(
        t, "estimator:\n  ros__parameters:\n    debug_image: false\n"))], "'graphs' is empty"),
    ("node-out-of-range", node_main, lambda g, t: ["estimator", "--params-file", str(node_file(
        t, graphs_yaml(g, "    matching:\n      rotation_candidates: 100000\n")))], "rotation_candidates"),
    ("node-wrong-type", node_main, lambda g, t: ["estimator", "--params-file", str(node_file(
        t, graphs_yaml(g, "    pose:\n      min_score: high\n")))], "min_score"),
    ("node-bad-transport", node_main, lambda g, t: ["estimator", "--params-file", str(node_file(
        t, graphs_yaml(g, "    image_transport: theora\n")))], "image_transport"),
    ("node-flag-unknown", node_main, lambda g, t: ["estimator", "--bogus"], "unrecognized"),
    # bags through play_bag.py
    ("bag-missing", play_bag, lambda g, t: [str(t / "none")], "cannot read bag"),
    ("bag-empty-folder", play_bag, lambda g, t: [str(mkdir(t / "empty"))], "cannot read bag"),
    ("bag-damaged", play_bag, lambda g, t: [str(damaged_bag(t))], "cannot read bag"),
    ("bag-no-images", play_bag, lambda g, t: [str(foreign_bag(t / "chat", [
        ("/chatter", "std_msgs/msg/String", STORE.types["std_msgs/msg/String"](data="hi"))]))], "no sensor_msgs"),
    ("bag-two-image-topics", play_bag, lambda g, t: [str(foreign_bag(t / "two", [
        bag_image(), ("/other/image", *bag_image()[1:])]))], "several image topics"),
    ("bag-bad-encoding", play_bag, lambda g, t: [str(foreign_bag(t / "enc", [bag_image("32FC1", step=32,
                                                                                        size=256)]))],
     "unsupported image encoding"),
    ("bag-short-data", play_bag, lambda g, t: [str(foreign_bag(t / "short", [bag_image(size=10)]))], "bytes"),
    ("bag-huge-claim", play_bag, lambda g, t: [str(foreign_bag(t / "huge", [bag_image(
        width=100_000, height=100_000, step=100_000, size=16)]))], "exceeds the limit"),
    ("bag-png-bomb", play_bag, lambda g, t: [str(foreign_bag(t / "pbomb", [bag_compressed(
        png_claiming(100_000, 100_000))]))], "exceeds the limit"),
    ("bag-compressed-garbage", play_bag, lambda g, t: [str(foreign_bag(t / "garbage", [bag_compressed(
        b"garbage" * 10)]))], "neither PNG nor JPEG"),
    ("bag-camera-info-nan", play_bag, lambda g, t: [str(foreign_bag(t / "knan", [
        bag_camera_info([math.nan] + K_GOOD[1:]), bag_image()]))], "finite"),
    ("bag-camera-info-zero", play_bag, lambda g, t: [str(foreign_bag(t / "kzero", [
        bag_camera_info([0.0] * 9), bag_image()]))], "focal lengths must be positive"),
    ("play-speed-zero", play_bag, lambda g, t: [str(t), "--speed", "0"], "positive"),
    ("play-timeout-negative", play_bag, lambda g, t: [str(t), "--timeout", "-1"], "positive"),
    ("play-reliability", play_bag, lambda g, t: [str(t), "--reliability", "sometimes"], "invalid choice"),
    # brepose-bag
    ("bag-cli-no-scene", bag_cli, lambda g, t: [str(t / "none"), str(t / "out")], "does not exist"),
    ("bag-cli-rate-zero", bag_cli, lambda g, t: [str(g["scene"]), str(t / "out"), "--rate", "0"], "positive"),
    ("bag-cli-rate-nan", bag_cli, lambda g, t: [str(g["scene"]), str(t / "out"), "--rate", "nan"], "positive"),
    ("bag-cli-exists", bag_cli, lambda g, t: [str(g["scene"]), str(mkdir(t / "out"))], "exists"),
    ("bag-cli-compression", bag_cli, lambda g, t: [str(g["scene"]), str(t / "out"), "--compressed", "gif"],
     "invalid choice"),
    # brepose-render and brepose-eval
    ("render-n-zero", render_cli, lambda g, t: ["builtin:cube", str(t / "s"), "--n", "0"], "positive integer"),
    ("render-occlusion-negative", render_cli, lambda g, t: ["builtin:cube", str(t / "s"), "--occlusion", "-1"],
     ">= 0"),
    ("render-unknown-builtin", render_cli, lambda g, t: ["builtin:nope", str(t / "s")], "unknown built-in part"),
    ("eval-no-scene", evaluate_cli, lambda g, t: [str(t / "none"), "--graph", str(g["graph"])], "does not exist"),
]


def plain_zip(tmp: Path) -> Path:
    path = tmp / "plain.brepose.npz"
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("readme.txt", "hello")
    return path


def flipped(g, tmp: Path) -> Path:
    data = bytearray(g["graph"].read_bytes())
    data[len(data) // 3] ^= 0xFF
    return write(tmp, "flip.brepose.npz", bytes(data))


def camera_file(tmp: Path, **changes) -> Path:
    camera = {"fx": 150.0, "fy": 150.0, "cx": 79.5, "cy": 59.5, "width": 160, "height": 120, **changes}
    camera = {k: v for k, v in camera.items() if v is not None}
    return write(tmp, "camera.json", json.dumps(camera))


def mkdir(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


def damaged_bag(tmp: Path) -> Path:
    write_bag(tmp / "damaged", [np.zeros((8, 8), np.uint8)], Camera(8.0, 8.0, 4.0, 4.0, 8, 8))
    storage = next((tmp / "damaged").glob("*.mcap"))
    storage.write_bytes(storage.read_bytes()[:200])
    return tmp / "damaged"


@pytest.mark.parametrize("case", COMMAND_CASES, ids=[c[0] for c in COMMAND_CASES])
def test_command_refuses_with_one_line_and_status_2(case, good, tmp_path, capsys):
    _, command, argv, expected = case
    try:
        status = command.main(argv(good, tmp_path))
    except SystemExit as exit_:  # argparse
        status = exit_.code
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("[")]  # [ROS log] lines
    assert status == 2, err
    assert len(lines) == 1 and "error" in lines[0] and "Traceback" not in err, err
    assert expected in lines[0], lines[0]


# -- the running node ---------------------------------------------------------------------

def rss_mb() -> float:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS")) / 1024.0


def raw(encoding: str, width: int, height: int, step: int, size: int) -> Image:
    return Image(encoding=encoding, width=width, height=height, step=step, data=bytes(size))


CAMERA = Camera(150.0, 150.0, 79.5, 59.5, 160, 120)

#: (id, Image) that must be answered with ERROR "bad image: ..."
BAD_IMAGES = [
    ("image-encoding", raw("32FC1", 160, 120, 640, 640 * 120)),
    ("image-step-short", raw("bgr8", 160, 120, 160, 160 * 120)),
    ("image-data-short", raw("mono8", 160, 120, 160, 100)),
    ("image-zero-size", raw("mono8", 0, 0, 0, 0)),
    ("image-huge-claim", raw("mono8", 100_000, 100_000, 100_000, 64)),
    ("image-yuv-odd-width", raw("yuv422", 159, 120, 318, 318 * 120)),
    ("image-bayer-short", raw("bayer_rggb8", 160, 120, 160, 160 * 119)),
    ("image-empty-data", raw("mono16", 160, 120, 320, 0)),
]


def bad_info(change) -> CameraInfo:
    info = camera_info_msg(CAMERA, Header())
    change(info)
    return info


#: (id, CameraInfo) that must make the next image an ERROR naming the CameraInfo
BAD_CAMERA_INFOS = [
    ("camera-info-uncalibrated", bad_info(lambda i: setattr(i, "k", [0.0] * 9))),
    ("camera-info-nan", bad_info(lambda i: setattr(i, "k", [math.nan] + K_GOOD[1:]))),
    ("camera-info-model", bad_info(lambda i: (setattr(i, "distortion_model", "equidistant"),
                                              setattr(i, "d", [0.1, 0.0, 0.0, 0.0])))),
    ("camera-info-d-length", bad_info(lambda i: setattr(i, "d", [0.1, 0.0, 0.0]))),
    ("camera-info-size", bad_info(lambda i: (setattr(i, "width", 320), setattr(i, "height", 240)))),
    ("camera-info-d-inf", bad_info(lambda i: setattr(i, "d", [math.inf, 0.0, 0.0, 0.0, 0.0]))),
]

#: (id, name, value) that must be refused with a reason while the node runs
BAD_PARAMETERS = [
    ("param-max-model-segments-zero", "matching.max_model_segments", 0),
    ("param-rotation-candidates-huge", "matching.rotation_candidates", 100000),
    ("param-min-score-nan", "pose.min_score", math.nan),
    ("param-workers-negative", "matching.workers", -1),
    ("param-blur-even", "edges.blur_size", 4),
    ("param-fx-inf", "fx", math.inf),
    ("param-string-for-int", "matching.shortlist_size", "many"),
    ("param-read-only-graphs", "graphs", ["other.brepose.npz"]),
    ("param-detector", "edges.detector", "canny"),
    ("param-hough-theta-tiny", "edges.hough_theta_deg", 1e-6),
]

KINDS = len(COMMAND_CASES) + len(BAD_IMAGES) + len(BAD_CAMERA_INFOS) + len(BAD_PARAMETERS) + 4  # + compressed


def test_the_corpus_has_at_least_60_kinds():
    assert KINDS >= 60, KINDS


@pytest.fixture
def ros():
    harness = Harness()
    yield harness
    harness.close()


@pytest.mark.ros
def test_node_answers_bad_input_with_errors_and_keeps_going(ros, good):
    ros.start_node({"graphs": [str(good["graph"])]})
    image = cv2.imread(str(good["image"]), cv2.IMREAD_UNCHANGED)
    camera = Camera.load(good["camera"])
    ros.answer(ros.publish(image, camera), 3 * TIMEOUT)  # warm-up: the first image pays the imports
    before = rss_mb()
    for _, bad in BAD_IMAGES:
        [status] = ros.answer(ros.publish(bad, camera))
        assert status.level == DiagnosticStatus.ERROR and status.message.startswith("bad image"), status.message
    node = ros.nodes[-1]
    for _, info in BAD_CAMERA_INFOS:
        info.header = ros.header()
        ros.info_pub.publish(info)
        wait_until(lambda: node.camera_info is not None and node.camera_info.header == info.header, TIMEOUT,
                   "the bad CameraInfo")
        [status] = ros.answer(ros.publish(image))
        assert status.level == DiagnosticStatus.ERROR and "CameraInfo" in status.message, status.message
    for _, name, value in BAD_PARAMETERS:
        before_value = node.get_parameter(name).value
        result = node.set_parameters([Parameter(name, value=value)])[0]
        assert not result.successful and result.reason, name
        assert node.get_parameter(name).value == before_value or (
            isinstance(before_value, float) and math.isnan(before_value))
    [status] = ros.answer(ros.publish(image, camera), 3 * TIMEOUT)
    assert status.level in (DiagnosticStatus.OK, DiagnosticStatus.WARN), status.message
    assert rss_mb() - before < 100, f"memory grew from {before:.0f} to {rss_mb():.0f} MB over the corpus"


@pytest.mark.ros
def test_node_answers_bad_compressed_images_with_errors(ros, good):
    node = ros.start_node({"graphs": [str(good["graph"])], "image_transport": "compressed"})
    publisher = ros.probe.create_publisher(CompressedImage, "image_raw/compressed", PUBLISHER_QOS["best_effort"])
    wait_until(lambda: publisher.get_subscription_count() > 0, TIMEOUT, "compressed subscription")
    camera = Camera.load(good["camera"])
    good_png = good["image"].read_bytes()
    bad = [("png", png_claiming(100_000, 100_000)), ("jpeg", jpeg_claiming(60_000, 60_000)),
           ("png", b"garbage" * 20), ("16UC1; compressedDepth", good_png)]
    before = rss_mb()
    for fmt, data in bad + [("png", good_png)]:
        header = ros.header()
        ros.info_pub.publish(camera_info_msg(camera, header))
        publisher.publish(CompressedImage(header=header, format=fmt, data=data))
        [status] = ros.answer(stamp_of(header), 3 * TIMEOUT)
        expected = DiagnosticStatus.ERROR if data is not good_png or "Depth" in fmt else status.level
        assert status.level == expected, (fmt, status.message)
    assert status.level != DiagnosticStatus.ERROR, "the good PNG after the bad ones was answered"
    assert rss_mb() - before < 100
    assert node.image_input.topic == "/image_raw/compressed"


def stamp_of(header) -> int:
    return header.stamp.sec * 1_000_000_000 + header.stamp.nanosec


"""Latency and frames/s through the ROS node against the library's own, in one process.

    python launch_free_scripts/demo.py --out out/demo      # once: graph + scene
    python bench/node_latency.py --demo out/demo

Rows:
- library: ``Estimator.estimate`` called directly, per ``matching.workers``; CPU/wall above 1
  means the views really ran on two cores at once;
- node lock-step: publish Image + CameraInfo, wait for the node's diagnostics of that image
  (latency = publish to diagnostics arrival, which follows the pose), with the patched
  executor (``messages.make_executor``) and rclpy's stock MultiThreadedExecutor;
- node at a camera rate: frames published at ``--rate`` Hz regardless of the node; the node
  answers the newest frame each time it is free and skips the rest.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")

import cv2  # noqa: E402
from rclpy.executors import MultiThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.ros.node import EstimatorNode  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.ros.messages import camera_info_msg, image_msg, make_executor, stamp_from_ns  # noqa: E402
from brepose_ros.ros.replay import Player, RosSession  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402

FRAME = "camera_optical_frame"
WARM_UP_NS, FIRST_NS = 10**18, 2 * 10**18


def row(name: str, latencies_ms: list[float], frames: int, seconds: float, extra: str = "") -> str:
    lat = sorted(latencies_ms)
    p90 = lat[min(len(lat) - 1, int(0.9 * len(lat)))] if lat else float("nan")
    median = statistics.median(lat) if lat else float("nan")
    return f"{name:<44} {median:>9.0f} {p90:>9.0f} {frames / seconds:>9.2f}  {extra}"


def library_rows(graph, images, camera, repeat: int) -> list[str]:
    rows = []
    for workers in (1, 2):
        estimator = Estimator(graph, EstimatorParams().with_flat({"matching.workers": workers}))
        estimator.estimate(images[0], camera)  # warm-up: caches, thread pool
        latencies, matching = [], []
        cpu, start = time.process_time(), time.perf_counter()
        for _ in range(repeat):
            for image in images:
                t0 = time.perf_counter()
                estimate = estimator.estimate(image, camera)
                latencies.append(1000.0 * (time.perf_counter() - t0))
                matching.append(1000.0 * estimate.timings["matching"])
        wall = time.perf_counter() - start
        estimator.close()
        rows.append(row(f"library, matching.workers={workers}", latencies, len(latencies), wall,
                        f"CPU/wall {(time.process_time() - cpu) / wall:.2f}, "
                        f"matching stage median {statistics.median(matching):.0f} ms"))
    return rows


def frames_at(images, camera, rate_hz: float, repeat: int, first_ns: int):
    """(stamp, Image, CameraInfo) messages ``1/rate_hz`` apart."""
    stamp = first_ns
    for _ in range(repeat):
        for image in images:
            header = Header(stamp=stamp_from_ns(stamp), frame_id=FRAME)
            yield stamp, image_msg(image, header), camera_info_msg(camera, header)
            stamp += int(1e9 / rate_hz)


def node_row(name: str, graph_path: Path, images, camera, executor_factory, mode: str,
             rate_hz: float, repeat: int) -> str:
    with RosSession(threads=2, executor_factory=executor_factory) as ros:
        ros.add(EstimatorNode(context=ros.context, parameter_overrides=[
            Parameter("graphs", value=[str(graph_path)]), Parameter("matching.workers", value=2)]))
        player = Player(ros.node("bench_player"))
        player.wait_for_node()
        player.play(frames_at(images[:1], camera, rate_hz, 1, WARM_UP_NS), "lockstep")
        cpu = time.process_time()
        playback = player.play(frames_at(images, camera, rate_hz, repeat, FIRST_NS), mode)
        if mode == "rate":  # the last frame may still be in work
            player.diagnostics.wait_for(max(playback.published_at), 10.0)
            playback.seconds = max(player.diagnostics.arrived.values()) - min(playback.published_at.values())
        answered = len(playback.answered(player.diagnostics))
        extra = (f"answered {answered}/{len(playback.published_at)}, "
                 f"CPU/wall {(time.process_time() - cpu) / playback.seconds:.2f}")
        return row(name, list(playback.latencies_ms(player.diagnostics).values()), answered, playback.seconds, extra)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demo", type=Path, default=Path("out/demo"),
                        help="output folder of launch_free_scripts/demo.py (graph and scene)")
    parser.add_argument("--repeat", type=int, default=1, help="passes over the scene's images")
    parser.add_argument("--rate", type=float, default=10.0, help="camera rate of the free-running row, Hz")
    args = parser.parse_args()
    graph_path = args.demo / "sample_bracket.brepose.npz"
    scene = load_scene(args.demo / "scene")
    images = [cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED) for entry in scene.entries]
    camera = scene.camera
    graph = AspectGraph.load(graph_path)

    print(f"{len(images)} images {camera.width}x{camera.height}, {graph.n_views} views, "
          f"{os.cpu_count()} CPUs; latency in ms\n")
    print(f"{'':<44} {'median':>9} {'p90':>9} {'frames/s':>9}")
    for line in library_rows(graph, images, camera, args.repeat):
        print(line, flush=True)

    def stock(threads, context):
        return MultiThreadedExecutor(num_threads=threads, context=context)

    runs = [("node lock-step, patched executor", make_executor, "lockstep"),
            ("node lock-step, stock MultiThreadedExecutor", stock, "lockstep"),
            (f"node at {args.rate:g} Hz, patched executor", make_executor, "rate")]
    for name, factory, mode in runs:
        print(node_row(name, graph_path, images, camera, factory, mode, args.rate, args.repeat), flush=True)


if __name__ == "__main__":
    main()

"""Soak: the estimator node in its own process, fed bgr8 640x480 frames at 30 Hz from this one.

    python launch_free_scripts/demo.py --out out/demo      # once: graph + 640x480 scene
    python bench/soak.py --demo out/demo                   # 10 minutes
    python bench/soak.py --demo out/demo --minutes 1       # a shorter run

The node is started as a user would (``python -m brepose_ros.ros.node --params-file``), on
a random ROS domain; this process publishes the scene's images round and round as bgr8 at
``--rate`` Hz, regardless of the node, like a camera driver (``--reliability``: what the
driver offers; the node follows it). The node answers the newest frame each time it is free
and skips the rest. Printed: the node's resident memory (VmRSS) after a warm-up and at the
end, with its peak between; frames published and answered; latency percentiles from publish
to the arrival of the frame's diagnostics; the node's own frames_skipped and frames_lost.
"""
from __future__ import annotations

import argparse
import os
import random
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.pop("ROS_AUTOMATIC_DISCOVERY_RANGE", None)  # two processes must discover each other
os.environ.setdefault("ROS_DOMAIN_ID", str(random.randint(100, 200)))  # and nobody else

import cv2  # noqa: E402
from std_msgs.msg import Header  # noqa: E402

from brepose_ros.ros.messages import PUBLISHER_QOS, camera_info_msg, image_msg, stamp_from_ns, status_values  # noqa: E402
from brepose_ros.ros.replay import Player, RosSession  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402

FRAME = "camera_optical_frame"
#: the node's memory is sampled this often, s
RSS_PERIOD = 10.0
WARM_UP_FRAMES = 5
#: RSS growth is also given from this time on, s
SETTLE_SECONDS = 60.0


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS")) / 1024.0


def start_node(graph: Path, folder: Path) -> tuple[subprocess.Popen, Path]:
    params = folder / "node.yaml"
    params.write_text(f"estimator:\n  ros__parameters:\n    graphs: [{graph.resolve()}]\n    debug_image: false\n")
    log = folder / "node.log"
    env = {k: v for k, v in os.environ.items() if k not in ("_ROS_WHEELS_BOOTSTRAP_COMPLETE", "LD_LIBRARY_PATH")}
    process = subprocess.Popen([sys.executable, "-m", "brepose_ros.ros.node", "--params-file", str(params)],
                               stdout=log.open("w"), stderr=subprocess.STDOUT, env=env)
    deadline = time.monotonic() + 60.0
    while "estimating" not in log.read_text():
        if process.poll() is not None or time.monotonic() > deadline:
            raise SystemExit(f"the node did not start:\n{log.read_text()}")
        time.sleep(0.2)
    return process, log


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))] if ordered else float("nan")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--demo", type=Path, default=Path("out/demo"),
                        help="output folder of launch_free_scripts/demo.py (graph and 640x480 scene)")
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the soak (default 10)")
    parser.add_argument("--rate", type=float, default=30.0, help="frames per second published (default 30)")
    parser.add_argument("--reliability", choices=PUBLISHER_QOS, default="reliable",
                        help="what the publisher offers (default reliable: docs/ros.md)")
    args = parser.parse_args()
    scene = load_scene(args.demo / "scene")
    images = [cv2.imread(str(entry.path), cv2.IMREAD_COLOR) for entry in scene.entries]  # bgr8 on the wire
    camera = scene.camera
    frames_total = int(args.minutes * 60 * args.rate)

    with tempfile.TemporaryDirectory() as tmp:
        node, log = start_node(args.demo / "sample_bracket.brepose.npz", Path(tmp))
        try:
            with RosSession() as ros:
                player = Player(ros.node("soak_camera"), reliability=args.reliability)
                player.wait_for_node(30.0)
                stamp = 10**18

                def frame(i: int) -> tuple:
                    header = Header(stamp=stamp_from_ns(stamp + i * int(1e9 / args.rate)), frame_id=FRAME)
                    return (stamp + i * int(1e9 / args.rate), image_msg(images[i % len(images)], header),
                            camera_info_msg(camera, header))

                player.play((frame(i) for i in range(WARM_UP_FRAMES)), "lockstep", timeout=60.0)
                stamp = 2 * 10**18
                rss = [(0.0, rss_mb(node.pid))]
                published: dict[int, float] = {}
                start = time.perf_counter()
                for i in range(frames_total):
                    delay = start + i / args.rate - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                    s, image, info = frame(i)
                    player.info_pub.publish(info)
                    published[s] = time.perf_counter()
                    player.image_pub.publish(image)
                    if time.perf_counter() - start - rss[-1][0] >= RSS_PERIOD:
                        rss.append((time.perf_counter() - start, rss_mb(node.pid)))
                seconds = time.perf_counter() - start
                time.sleep(2.0)  # the last frames' answers
                rss.append((time.perf_counter() - start, rss_mb(node.pid)))
                arrived = player.diagnostics.arrived
                answered = [s for s in published if s in arrived]
                latencies = [1000.0 * (arrived[s] - published[s]) for s in answered]
                last = status_values(player.diagnostics.by_stamp[max(answered)].status[0]) if answered else {}
        finally:
            node.terminate()
            node.wait(timeout=30.0)

    first, end = rss[0][1], rss[-1][1]
    peak = max(mb for _, mb in rss)
    # the first minute fills the allocator's pools and the estimator's caches; growth after it
    # is what a leak would show
    settled = next((mb for t, mb in rss if t >= SETTLE_SECONDS), None)
    print(f"{len(images)} images {camera.width}x{camera.height} bgr8 at {args.rate:g} Hz for {seconds / 60:.1f} min, "
          f"{args.reliability} publisher, node in its own process")
    print(f"node RSS: {first:.0f} MB after warm-up, {end:.0f} MB at the end ({100 * (end - first) / first:+.1f} %), "
          f"peak {peak:.0f} MB" + (f"; {settled:.0f} MB after {SETTLE_SECONDS:.0f} s, "
                                   f"{100 * (end - settled) / settled:+.1f} % since" if settled else ""))
    print(f"frames: {len(published)} published, {len(answered)} answered "
          f"({len(answered) / seconds:.2f}/s); node: frames_skipped {last.get('frames_skipped', '?')}, "
          f"frames_lost {last.get('frames_lost', '?')}, input_hz {last.get('input_hz', '?')}")
    print(f"latency, publish to diagnostics, ms: p50 {percentile(latencies, 0.5):.0f}, "
          f"p90 {percentile(latencies, 0.9):.0f}, p99 {percentile(latencies, 0.99):.0f}, "
          f"max {max(latencies, default=float('nan')):.0f}"
          + (f", mean {statistics.mean(latencies):.0f}" if latencies else ""))
    print("RSS samples (s, MB): " + ", ".join(f"{t:.0f} {mb:.0f}" for t, mb in rss))
    return 0


if __name__ == "__main__":
    sys.exit(main())

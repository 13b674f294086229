"""The whole path in one command: STEP model -> aspect graph -> camera bag -> ROS node -> poses.

    python launch_free_scripts/demo.py --out out/demo

1. writes the bundled sample part's STEP file and compiles its aspect graph (once: a graph
   that still matches the STEP file and the view spacing is reused);
2. renders a synthetic scene with exact ground truth and records it as a rosbag2 of
   Image + CameraInfo, like a camera driver would (also reused when present);
3. starts the estimator node in this process, plays the bag lock-step into its topics and
   records what it publishes;
4. prints every pose with its error against the ground truth and the summary metrics of
   CONVENTIONS.md, and leaves predictions.json and debug overlays in ``--out``.

Delete ``--out`` to start from scratch.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
from pathlib import Path

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "OFF")  # everything runs in this process

import cv2  # noqa: E402
import numpy as np  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from sensor_msgs.msg import Image  # noqa: E402

from brepose_ros.synthetic import shapes  # noqa: E402
from brepose_ros.offline.compiler import DEFAULT_STEP_DEG, compile_aspect_graph  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph, AspectGraphError  # noqa: E402
from brepose_ros.ros.bags import write_scene_bag  # noqa: E402
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.evaluation.metrics import (ModelPoints, found_correct, pose_errors, summarise,  # noqa: E402
                                           write_predictions)
from brepose_ros.ros.node import EstimatorNode  # noqa: E402
from brepose_ros.ros.replay import Player, PoseRecorder, RosSession, bag_frames, scene_names  # noqa: E402
from brepose_ros.ros.messages import image_from_msg  # noqa: E402
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402

PART = "sample_bracket"


def graph_for(step: Path, path: Path, step_deg: float) -> Path:
    """The compiled aspect graph of ``step``, compiled only if ``path`` is missing or stale."""
    try:
        if AspectGraph.load(path, step_path=step).params.get("step_deg") == step_deg:
            print(f"reusing {path}")
            return path
    except AspectGraphError:
        pass
    print(f"compiling the aspect graph of {step.name} ({step_deg:g} degrees between views)")
    return compile_aspect_graph(step, step_deg=step_deg).save(path)


def scene_and_bag(step: Path, out: Path, images: int, seed: int) -> tuple[Path, Path]:
    scene, bag = out / "scene", out / "bag"  # not *.bag: rosbags reads such a path as a ROS 1 bag
    if not (scene / "gt.json").is_file():
        print(f"rendering {images} images into {scene}")
        generate_scene(step, scene, images, seed=seed, config=SceneConfig(clutter=2), progress=True)
    if not bag.exists():
        write_scene_bag(scene, bag)
        print(f"recorded {bag}")
    return scene, bag


class OverlaySaver:
    """Writes the node's first ``count`` debug images to ``folder`` as PNG."""

    def __init__(self, node, topic: str, folder: Path, count: int):
        self.folder, self.count, self.saved = folder, count, []
        folder.mkdir(parents=True, exist_ok=True)
        node.create_subscription(Image, topic, self._on_image, 10)

    def _on_image(self, msg: Image) -> None:
        if len(self.saved) < self.count:
            path = self.folder / f"{len(self.saved):06d}.png"
            cv2.imwrite(str(path), image_from_msg(msg))
            self.saved.append(path)


def run_node(graph: Path, bag: Path, names: dict[int, str], out: Path, overlays: int):
    """Play the bag lock-step through an in-process node; predictions and latencies."""
    with RosSession() as ros:
        node = ros.add(EstimatorNode(context=ros.context, parameter_overrides=[
            Parameter("graphs", value=[str(graph)]), Parameter("part_names", value=[PART])]))
        part = node.parts[0]
        client = ros.node("demo")
        player = Player(client)
        recorder = PoseRecorder(client, part.pose_pub.topic_name, part.status_name, player.diagnostics)
        saver = OverlaySaver(client, part.debug_pub.topic_name, out / "overlays", overlays)
        player.wait_for_node()
        playback = player.play(bag_frames(bag), "lockstep", timeout=60.0)
        predictions = recorder.predictions(names)
        latency = {names[s]: ms for s, ms in playback.latencies_ms(player.diagnostics).items()}
        return predictions, latency, playback.seconds, saver.saved


def report(predictions: list[dict], latency: dict[str, float], scene: Path, seconds: float) -> dict:
    """Print each pose against its ground truth; the summary metrics."""
    loaded = load_scene(scene)
    mesh = tessellate(load_step(loaded.step))
    model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
    by_image = {p["image"]: p for p in predictions}
    errors = []
    print(f"\n{'image':<20} {'found':>5} {'score':>6} {'err.ratio':>9} {'rot deg':>8} {'trans mm':>9} "
          f"{'er':>7} {'ADD-S':>6} {'ms':>6}")
    for truth in loaded.entries:
        p = by_image.get(truth.image)
        found = p is not None and p["R"] is not None
        e = pose_errors(np.reshape(p["R"], (3, 3)), np.array(p["t"]), truth.R, truth.t, model) if found else None
        errors.append(e)
        numbers = (f"{e.rotation_deg:>8.2f} {e.translation_mm:>9.2f} {e.error_rate:>7.4f} {e.add_s:>6.3f}"
                   if e else f"{'-':>8} {'-':>9} {'-':>7} {'-':>6}")
        score = f"{p['score']:>6.2f} {p['error_ratio']:>9.2f}" if p else f"{'-':>6} {'-':>9}"
        print(f"{truth.image:<20} {str(found):>5} {score} {numbers} {latency.get(truth.image, float('nan')):>6.0f}")
    summary = summarise(errors)
    summary["frames_per_s"] = len(predictions) / seconds if seconds else float("nan")
    summary["median_latency_ms"] = statistics.median(latency.values()) if latency else float("nan")
    print(f"\n{found_correct(errors)}; median error {summary['median_rotation_deg']:.2f} degrees, "
          f"{summary['median_translation_mm']:.2f} mm; median latency {summary['median_latency_ms']:.0f} ms, "
          f"{summary['frames_per_s']:.1f} frames/s")
    return summary


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], epilog="example: make demo (= python "
                                     "launch_free_scripts/demo.py --out out/demo); delete out/demo to start afresh")
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    parser.add_argument("--images", type=int, default=8, help="images in the synthetic scene")
    parser.add_argument("--seed", type=int, default=0, help="scene random seed")
    parser.add_argument("--step-deg", type=float, default=DEFAULT_STEP_DEG, help="aspect graph view spacing, degrees")
    parser.add_argument("--overlays", type=int, default=4, help="debug overlay images to keep")
    args = parser.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)

    step = out / f"{PART}.step"
    if not step.is_file():  # a new export would change the file's sha256 and stale the graph
        shapes.export_step(PART, step)
    graph = graph_for(step, out / f"{PART}.brepose.npz", args.step_deg)
    scene, bag = scene_and_bag(step, out, args.images, args.seed)
    print("running the estimator node on the bag, lock-step")
    predictions, latency, seconds, overlays = run_node(graph, bag, scene_names(bag, scene), out, args.overlays)
    write_predictions(out / "predictions.json", predictions)
    report(predictions, latency, scene, seconds)
    print(f"\nwrote {out / 'predictions.json'} and {len(overlays)} overlays in {out / 'overlays'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

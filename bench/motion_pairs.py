"""What the camera's motion blur costs, on the very same images: each bench image
re-rendered with its motion blur changed, everything else (pose, lights, props, background
and noise draws) as the scene has it, and the estimator run on both.

    python bench/motion_pairs.py [--parts ...] [--conditions clean clutter] [--n 16] [--start 0]
                                 [--length 7] [group.key=value ...]

Images that have a motion blur (gt.json's ``look.motion``) are re-rendered without it;
images without one get a straight one of ``--length`` pixels (0: left out) in a direction
drawn from (seed, image index). The bench's split by look compares different images, whose
light and surface differ too (docs/results/blur.md); this pairs them. Per image: the
stored image's outcome and the re-rendered one's (R right up to symmetry, w a wrong pose
reported found, - nothing found) with their scores, then the totals and the images that
changed. Overrides (``edges.blur_size=7``) apply to both runs, so a fix can be measured by
how much of the blur's cost it takes back.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.accuracy import (CONDITIONS, PARTS, SPAN, add_scene_arguments, distractor_meshes,  # noqa: E402
                            overridden_params, scene_path, step_file)
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, pose_errors  # noqa: E402
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402
from brepose_ros.synthetic.scenes import SceneConfig, render_image  # noqa: E402

SEED = 100  # bench/accuracy.py's scenes


def changed_motion(look_record: dict, length: float, index: int):
    """The look change of one image (``render_image``'s ``change_look``): the motion blur taken
    away where there is one, else one of ``length`` pixels; None when nothing changes."""
    if look_record["motion"] > 0:
        return lambda look: dataclasses.replace(look, motion=0.0)
    if length <= 0:
        return None
    angle = float(np.random.default_rng([SEED, index, 1]).uniform(0.0, np.pi))
    return lambda look: dataclasses.replace(look, motion=length, motion_angle=angle)


def outcome(estimator: Estimator, image: np.ndarray, camera, entry, model, graph) -> tuple[str, float]:
    """R (right up to symmetry), w (a wrong pose found) or - (nothing found), and the score."""
    estimate = estimator.estimate(image, camera)
    if not estimate.found:
        return "-", estimate.score
    errors = pose_errors(estimate.R, estimate.t, entry.R, entry.t, model, graph)
    return ("R" if errors.success_sym else "w"), estimate.score


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, parts=list(PARTS), conditions=["clean", "clutter"], n=16, start=True)
    parser.add_argument("--length", type=float, default=7.0,
                        help="motion blur given to images without one, pixels (0: those images are left out)")
    parser.add_argument("overrides", nargs="*", help="parameter overrides group.key=value")
    args = parser.parse_args(argv)
    params = overridden_params(args.overrides)
    cache = REPO / "data" / "bench"
    distractors = distractor_meshes(cache)
    #: per group (blur removed / added), stored and changed: [images, right, wrong found]
    counts = {group: {"stored": [0, 0, 0], "changed": [0, 0, 0]} for group in ("removed", "added")}
    moved = []
    print("| part | condition | image | motion px | stored | changed |\n|---|---|---|---|---|---|")
    for name in args.parts:
        step = step_file(PARTS[name], cache)
        if step is None:
            continue
        part = load_step(step)
        mesh = tessellate(part)  # renders the images and measures the poses
        graph = AspectGraph.load(cached_graph_path(step, cache, 5.0))
        model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        estimator = Estimator(graph, params)
        for condition in args.conditions:
            folder = scene_path(cache, name, condition)
            scene = load_scene(folder)
            looks = [record["look"] for record in json.loads((folder / "gt.json").read_text())]
            config = SceneConfig(span=SPAN, look="varied", **CONDITIONS[condition])
            for i in range(args.start, min(args.start + args.n, len(scene.entries))):
                change = changed_motion(looks[i], args.length, i)
                if change is None:
                    continue
                entry = scene.entries[i]
                stored = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
                changed = render_image(mesh, part.center, config, SEED, i, distractors, change)[0]
                group = "removed" if looks[i]["motion"] > 0 else "added"
                results = {}
                for key, image in (("stored", stored), ("changed", changed)):
                    results[key] = outcome(estimator, image, scene.camera, entry, model, graph)
                    tally = counts[group][key]
                    tally[0] += 1
                    tally[1] += results[key][0] == "R"
                    tally[2] += results[key][0] == "w"
                motion = f"{looks[i]['motion']:.1f} -> {0.0 if looks[i]['motion'] > 0 else args.length:.1f}"
                print(f"| {name} | {condition} | {i} | {motion} | {results['stored'][0]} {results['stored'][1]:.2f} "
                      f"| {results['changed'][0]} {results['changed'][1]:.2f} |", flush=True)
                if results["stored"][0] != results["changed"][0]:
                    moved.append(f"{name} {condition} {i}: {results['stored'][0]} -> {results['changed'][0]}")
        estimator.close()
    for group, tallies in counts.items():
        (n, right, wrong), (_, right_after, wrong_after) = tallies["stored"], tallies["changed"]
        if n:
            print(f"motion blur {group} on {n} images: right {right} -> {right_after}, "
                  f"wrong found {wrong} -> {wrong_after}")
    print("changed outcomes:", "; ".join(moved) or "none")
    return 0


if __name__ == "__main__":
    sys.exit(main())

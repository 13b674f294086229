"""A known working distance (``pose.min_distance`` / ``max_distance``) against none, image by image.

    python bench/known_distance.py [--n 6] [--start 64] [--ratios 1.25 1.5] [--parts sharp_bracket ...]
                                   [--conditions clean clutter occl30+clutter] [--label NAME]

Each image is estimated at default parameters and, for each RATIO, with the working range
set to the true distance of the part's model centre divided and multiplied by RATIO (a user
who knows the camera-to-part distance within -20 / +25 % for 1.25), in one process with one
estimator, the order of the settings turning every image (the machine is shared: times are
comparable only within a run). Success is CONVENTIONS.md's (rotation < 5 degrees,
translation < 5 % of the diameter, and found), also up to the part's exact symmetries; a
found pose wrong even up to them is a wrong detection. Scenes are bench/accuracy.py's
(varied look, seed 100, cached in data/bench); records go to
data/bench/results/known_distance_LABEL.json.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.accuracy import (PARTS, TUNING, add_scene_arguments, graph_and_model, part_set, scene_path,  # noqa: E402
                            step_file)
from brepose_ros.evaluation.metrics import pose_errors  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402


def setting_label(ratio: float) -> str:
    return "default" if ratio == 0 else f"x/{ratio:g}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=6, parts=TUNING, conditions=["clean", "clutter", "occl30+clutter"], start=True)
    parser.add_argument("--ratios", type=float, nargs="+", default=[1.25, 1.5])
    parser.add_argument("--label", default="run")
    args = parser.parse_args(argv)
    if any(r <= 1 for r in args.ratios):
        parser.error("--ratios must be above 1")
    cache = REPO / "data" / "bench"
    out = cache / "results" / f"known_distance_{args.label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    ratios = [0.0, *args.ratios]
    default = EstimatorParams()
    rows = []
    for name in args.parts:
        graph, model = graph_and_model(step_file(PARTS[name], cache), cache)
        estimator = Estimator(graph, default)
        for condition in args.conditions:
            scene = load_scene(scene_path(cache, name, condition))
            for i, entry in enumerate(scene.entries[args.start:args.start + args.n], start=args.start):
                image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
                distance = float(np.linalg.norm(entry.R @ graph.model_center + entry.t))
                row = {"set": part_set(name), "part": name, "condition": condition, "image": i}
                for ratio in ratios[i % len(ratios):] + ratios[:i % len(ratios)]:
                    estimator.params = default if ratio == 0 else default.with_flat(
                        {"pose.min_distance": distance / ratio, "pose.max_distance": distance * ratio})
                    start = time.perf_counter()
                    estimate = estimator.estimate(image, scene.camera)
                    ms = 1000 * (time.perf_counter() - start)
                    errors = (pose_errors(estimate.R, estimate.t, entry.R, entry.t, model, graph)
                              if estimate.found else None)
                    row[setting_label(ratio)] = {
                        "ms": ms, "success": bool(errors and errors.success),
                        "success_sym": bool(errors and errors.success_sym), "found": bool(estimate.found),
                        "score": float(estimate.score), "depth_ratio": estimate.distance / distance}
                rows.append(row)
                print(f"{name} {condition} {i}: " + "  ".join(
                    f"{label} {int(row[label]['success'])}/{int(row[label]['success_sym'])}/"
                    f"{int(row[label]['found'])} {row[label]['score']:.2f} d{row[label]['depth_ratio']:.2f} "
                    f"{row[label]['ms']:.0f} ms" for label in map(setting_label, ratios)), flush=True)
                out.write_text(json.dumps(rows))
        estimator.close()
    print_table(rows, [setting_label(r) for r in ratios])
    return 0


def print_table(rows: list[dict], labels: list[str]) -> None:
    """Per set and condition, each setting's success / success up to symmetry / found poses
    wrong even up to symmetry / median ms."""
    print("\nsuccess / up to symmetry / wrong found poses / median ms\n")
    print("| set | condition | images | " + " | ".join(labels) + " |")
    print("|---|---|---|" + "---|" * len(labels))
    for key in dict.fromkeys((r["set"], r["condition"]) for r in rows):
        group = [r for r in rows if (r["set"], r["condition"]) == key]
        cells = [f"{np.mean([r[s]['success'] for r in group]):.2f}"
                 f" / {np.mean([r[s]['success_sym'] for r in group]):.2f}"
                 f" / {sum(r[s]['found'] and not r[s]['success_sym'] for r in group)}"
                 f" / {np.median([r[s]['ms'] for r in group]):.0f}" for s in labels]
        print(f"| {key[0]} | {key[1]} | {len(group)} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    sys.exit(main())

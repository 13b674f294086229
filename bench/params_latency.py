"""Time per image of the estimator under two or more parameter files, on the same images,
the files alternating image by image (the order turned every round), so that a machine busy
with other jobs slows each alike and the ratios stay fair.

    python bench/params_latency.py --params config/estimator.yaml config/learned.yaml
                                   [--parts sharp_bracket rounded_bracket] [--n 6] [--rounds 2]

Scenes: bench/accuracy.py's clean and occl20+clutter scenes (varied look) of each part,
graphs at 10 degrees (data/bench/). Prints the median ms per image of each file, for the
full pipeline and the paper's method alone, and the ratio of the summed times to the first.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import PARTS, add_scene_arguments, distractor_meshes, scene, step_file  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--params", type=Path, nargs="+", required=True)
    add_scene_arguments(parser, n=6, parts=["sharp_bracket", "rounded_bracket"], conditions=["clean", "occl20+clutter"])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--step-deg", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=100)
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    sets = [EstimatorParams.load(p) for p in args.params]
    distractors = distractor_meshes(cache)
    times = {(i, paper): [] for i in range(len(sets)) for paper in (False, True)}
    for name in args.parts:
        step = step_file(PARTS[name], cache)
        estimator = Estimator(AspectGraph.load(cached_graph_path(step, cache, args.step_deg)))
        for condition in args.conditions:
            loaded = scene(cache, name, step, condition, args.n, distractors, seed=args.seed)
            images = [cv2.imread(str(e.path), cv2.IMREAD_UNCHANGED) for e in loaded.entries[:args.n]]
            for round_ in range(args.rounds):
                for image in images:
                    order = list(range(len(sets)))[:: 1 if round_ % 2 == 0 else -1]
                    for i in order:
                        for paper in (False, True):
                            estimator.params = sets[i]
                            estimate = estimator.estimate(image, loaded.camera, paper_only=paper)
                            times[(i, paper)].append(estimate.timings["total"] * 1000.0 if estimate.timings.get(
                                "total") else np.nan)
        estimator.close()
    print(f"{args.n} images x {len(args.conditions)} conditions x {len(args.parts)} parts x {args.rounds} rounds\n")
    print("| parameters | full: median ms | full: time ratio | paper: median ms | paper: time ratio |")
    print("|---|---|---|---|---|")
    for i, path in enumerate(args.params):
        cells = []
        for paper in (False, True):
            t = np.array(times[(i, paper)])
            ratio = np.nansum(t) / np.nansum(times[(0, paper)])
            cells.append(f"{np.nanmedian(t):.0f} | {ratio:.2f}")
        print(f"| {path.name} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

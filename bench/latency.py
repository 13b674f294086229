"""Per-image latency of the estimator: stage timings against the number of views and
worker threads, the start-up time and the peak memory.

    python bench/latency.py [--views 500 1505 2500 10000] [--workers 1 2] [--n 6] [--part sharp_bracket]

Graphs (golden-spiral sampling with the step that gives about that many views) and the
clean scene are cached in data/bench/; compiling the 10,000-view sharp_bracket takes
about two minutes on 2 cores. Times are medians over the scene's images; with other jobs
on the machine they are upper bounds. "setup s" is loading the graph and building the
estimator's view library, what a node pays once at start.
"""
from __future__ import annotations

import argparse
import resource
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import part_step  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.synthetic.scenes import generate_scene  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402
from brepose_ros.viewsphere import fibonacci_step  # noqa: E402

STAGES = ("edges", "prefilter", "matching", "refinement", "total")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, nargs="*", default=[500, 1505, 2500, 10000])
    parser.add_argument("--workers", type=int, nargs="*", default=[1, 2])
    parser.add_argument("--n", type=int, default=6)
    parser.add_argument("--part", default="sharp_bracket")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    cache.mkdir(parents=True, exist_ok=True)
    step = part_step(args.part, cache)
    folder = cache / f"scene_{step.stem}_latency_{args.n}"
    if not (folder / "gt.json").exists():
        generate_scene(step, folder, args.n, seed=7)
    scene = load_scene(folder)
    images = [cv2.imread(str(e.path), cv2.IMREAD_UNCHANGED) for e in scene.entries]

    print(f"| views | workers | {' | '.join(s + ' ms' for s in STAGES)} | images/s | setup s | peak RSS MB |")
    print("|" + "---|" * (len(STAGES) + 5))
    for views in args.views:
        path = cached_graph_path(step, cache, fibonacci_step(views), label=f"{views}views")
        for workers in args.workers:
            start = time.perf_counter()
            graph = AspectGraph.load(path)
            estimator = Estimator(graph, EstimatorParams().with_flat({"matching.workers": workers}))
            setup = time.perf_counter() - start
            timings = {s: [] for s in STAGES}
            for image in images:
                estimate = estimator.estimate(image, scene.camera)
                for s in STAGES:
                    timings[s].append(estimate.timings.get(s, 0.0) * 1000)
            estimator.close()
            medians = [float(np.median(timings[s])) for s in STAGES]
            peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
            print(f"| {graph.n_views} | {workers} | {' | '.join(f'{m:.0f}' for m in medians)} | "
                  f"{1000 / medians[-1]:.2f} | {setup:.1f} | {peak:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Per-image latency of the estimator against worker threads, parts estimated at once and
the number of views, on clean and occluded scenes; start-up and first-image time.

    python bench/latency.py [--views 500 2500 10000] [--workers 1 2 4] [--parts 1 2 4]
                            [--scenes clean occluded] [--n 6] [--rounds 2] [--part sharp_bracket]
                            [--look plain|varied] [--tables budgets --budgets 0 100 250] [--params FILE]

Four tables, each measured within one run with the settings alternating image by image
(the order turns every round), so that a machine busy with other jobs slows every setting
alike and the ratios stay fair while the absolute times are upper bounds:

- workers: ``matching.workers`` threads for one image; ms per image (median), images/s
  (1 / mean), the speed-up against the first setting (ratio of the summed times), whether
  every setting gave the same poses to the bit, and the CPU time per image of all threads
  (mean; on a machine busy with other jobs it is what one worker would take alone, since
  waiting for a core costs wall time but no CPU time);
- parts: P estimators (P copies of the graph, each with ``--part-workers`` threads) on the
  same image at once, one thread per part as the node runs them, the image's edges found
  once for all parts as the node does ("once") or by each part ("per part", as before the
  node shared them); wall time per image and its ratio to one part;
- start: in a fresh process, as a node starts: loading the graph and building the
  estimator ("setup s"), the first image's time, the steady state (the median of the later
  images), and the first image's time over its own once the rest have run (what starting
  costs, apart from how hard that image is);
- budgets (only when asked): ``search.time_budget_ms`` per image, ms per image (median,
  90th percentile, most), how many images left a step out, and how many kept the pose
  found without a budget (the first setting).

The load average is printed before each table and at the end.

Graphs (golden-spiral sampling with the step that gives about that many views) and scenes
(clean; occluded = 30 % occlusion, off-centre, 3 clutter objects; ``--look``: the plain look of
the first sessions, or the bench's varied light, backgrounds, blur and noise, where the later
generators run far more often) are cached in data/bench/; compiling the 10,000-view
sharp_bracket takes about two minutes on 2 cores.
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import CONDITIONS, step_file  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.workers import WorkerPool  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402
from brepose_ros.synthetic.scenes import LOOKS, SceneConfig, generate_scene  # noqa: E402
from brepose_ros.viewsphere import fibonacci_step  # noqa: E402

STAGES = ("edges", "prefilter", "matching", "refinement", "search", "total")
SCENES = {"clean": "clean", "occluded": "occl30+clutter"}


def with_workers(workers: int, base: EstimatorParams | None = None) -> EstimatorParams:
    return (base or EstimatorParams()).with_flat({"matching.workers": workers})


def pose_key(estimate) -> tuple:
    return (None if estimate.R is None else estimate.R.tobytes(), None if estimate.t is None else estimate.t.tobytes(),
            estimate.score)


def alternate(settings: list, images: list, rounds: int, run) -> dict:
    """``run(setting, image)`` -> (seconds, result) for every image and setting, the settings
    alternating image by image, their order turned each round; {setting: [(s, result)]}."""
    out = {s: [] for s in settings}
    for r in range(rounds):
        order = settings[r % len(settings):] + settings[:r % len(settings)]
        for image in images:
            for s in order:
                out[s].append(run(s, image))
    return out


def summary(seconds: list[float]) -> tuple[float, float]:
    """Median ms per image and images/s (1 / mean)."""
    return 1000.0 * float(np.median(seconds)), len(seconds) / float(np.sum(seconds))


def workers_table(graph: AspectGraph, scene, images, workers: list[int], rounds: int,
                  base: EstimatorParams) -> list[str]:
    estimators = {w: Estimator(graph, with_workers(w, base)) for w in workers}
    for e in estimators.values():
        e.estimate(images[0], scene.camera)  # each pool's first image is not the steady state

    def run(w, image):
        start, cpu = time.perf_counter(), time.process_time()
        estimate = estimators[w].estimate(image, scene.camera)
        estimate.timings["cpu"] = time.process_time() - cpu
        return time.perf_counter() - start, estimate

    results = alternate(workers, images, rounds, run)
    for e in estimators.values():
        e.close()
    same = all(len({pose_key(results[w][i][1]) for w in workers}) == 1 for i in range(len(results[workers[0]])))
    base = sum(s for s, _ in results[workers[0]])
    rows = []
    for w in workers:
        seconds = [s for s, _ in results[w]]
        stages = [1000.0 * float(np.median([e.timings.get(k, 0.0) for _, e in results[w]])) for k in STAGES[:-1]]
        ms, rate = summary(seconds)
        cpu = 1000.0 * float(np.mean([e.timings["cpu"] for _, e in results[w]]))
        rows.append(f"| {w} | {' | '.join(f'{m:.0f}' for m in stages)} | {ms:.0f} | {rate:.1f} | "
                    f"{base / sum(seconds):.2f} | {'yes' if same else 'NO'} | {cpu:.0f} |")
    return rows


def parts_table(graph: AspectGraph, scene, images, parts: list[int], part_workers: int, rounds: int,
                base: EstimatorParams) -> list[str]:
    estimators = [Estimator(graph, with_workers(part_workers, base)) for _ in range(max(parts))]
    # (parts, edges shared): more than one part finds the image's edges once for all, as the
    # node does (Estimator.detect), or each its own, the node before it shared them
    settings = [(p, shared) for p in parts for shared in ((True, False) if p > 1 else (True,))]
    threads = {p: WorkerPool(p) for p in parts}
    for e in estimators:
        e.estimate(images[0], scene.camera)

    def run(setting, image):
        p, shared = setting
        start = time.perf_counter()
        frame = estimators[0].detect(image, scene.camera, estimators[1:p]) if shared and p > 1 else None
        threads[p].map(lambda e: e.estimate(image, scene.camera, frame=frame), estimators[:p])
        return time.perf_counter() - start, None

    results = alternate(settings, images, rounds, run)
    for e in estimators:
        e.close()
    for pool in threads.values():
        pool.close()
    base = float(np.sum([s for s, _ in results[settings[0]]]))
    rows = []
    for p, shared in settings:
        seconds = [s for s, _ in results[(p, shared)]]
        ms, rate = summary(seconds)
        rows.append(f"| {p} | {'once' if shared else 'per part'} | {part_workers} | {ms:.0f} | {rate * p:.1f} | "
                    f"{sum(seconds) / base:.2f} |")
    return rows


def budgets_table(graph: AspectGraph, scene, images, budgets: list[float], rounds: int,
                  base: EstimatorParams) -> list[str]:
    estimators = {b: Estimator(graph, base.with_flat({"search.time_budget_ms": b})) for b in budgets}
    for e in estimators.values():
        e.estimate(images[0], scene.camera)  # each step's cost timed once before the budget judges it

    def run(b, image):
        start = time.perf_counter()
        estimate = estimators[b].estimate(image, scene.camera)
        return time.perf_counter() - start, estimate

    results = alternate(budgets, images, rounds, run)
    for e in estimators.values():
        e.close()
    unbudgeted = [pose_key(e) for _, e in results[budgets[0]]]
    rows = []
    for b in budgets:
        ms = 1000.0 * np.array([s for s, _ in results[b]])
        cut = sum(bool(e.skipped) for _, e in results[b])
        same = sum(pose_key(e) == key for (_, e), key in zip(results[b], unbudgeted))
        rows.append(f"| {b:g} | {np.median(ms):.0f} | {np.percentile(ms, 90):.0f} | {ms.max():.0f} | "
                    f"{cut} of {len(ms)} | {same} of {len(ms)} |")
    return rows


def start_row(path: Path, scene, images, workers: int, base: EstimatorParams) -> str:
    start = time.perf_counter()
    estimator = Estimator(AspectGraph.load(path), with_workers(workers, base))
    setup = time.perf_counter() - start
    seconds = []
    for image in images:
        start = time.perf_counter()
        estimator.estimate(image, scene.camera)
        seconds.append(time.perf_counter() - start)
    start = time.perf_counter()
    estimator.estimate(images[0], scene.camera)
    again = time.perf_counter() - start
    estimator.close()
    steady = float(np.median(seconds[1:]))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return (f"| {setup:.1f} | {1000 * seconds[0]:.0f} | {1000 * steady:.0f} | {seconds[0] / steady:.2f} | "
            f"{1000 * again:.0f} | {seconds[0] / again:.2f} | {peak:.0f} |")


def latency_scene(step: Path, cache: Path, name: str, n: int, look: str = "plain") -> tuple:
    """The cached latency scene ``name`` (a key of ``SCENES``) of ``n`` images in ``look``,
    made on first use, and its images read."""
    folder = cache / (f"scene_{step.stem}_latency_{name}_{n}" + ("" if look == "plain" else f"_{look}"))
    if not (folder / "gt.json").exists():
        generate_scene(step, folder, n, seed=7, config=SceneConfig(look=look, **CONDITIONS[SCENES[name]]))
    scene = load_scene(folder)
    return scene, [cv2.imread(str(e.path), cv2.IMREAD_UNCHANGED) for e in scene.entries]


def load_average() -> str:
    """The machine's load average (1, 5, 15 min) to print beside a table: the ratios hold
    under load, the absolute times do not."""
    return "\nload average " + " ".join(f"{x:.2f}" for x in os.getloadavg())


def print_table(header: list[str], paths: dict, scenes: dict, rows_of) -> None:
    """One table: the load average, the header, and ``rows_of(graph, scene, images)``'s rows
    (the columns after views and scene) for every graph and scene."""
    print(load_average())
    print("\n| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for path in paths.values():
        graph = AspectGraph.load(path)
        for name, (scene, images) in scenes.items():
            for row in rows_of(graph, scene, images):
                print(f"| {graph.n_views} | {name} {row}", flush=True)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, nargs="*", default=[500, 2500, 10000])
    parser.add_argument("--workers", type=int, nargs="*", default=[1, 2, 4])
    parser.add_argument("--parts", type=int, nargs="*", default=[1, 2, 4])
    parser.add_argument("--part-workers", type=int, default=0, help="matching.workers of each part (0 = cores)")
    parser.add_argument("--scenes", nargs="*", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--tables", nargs="*", default=["workers", "parts", "start"],
                        choices=["workers", "parts", "start", "budgets"])
    parser.add_argument("--budgets", type=float, nargs="*", default=[0, 100, 250],
                        help="search.time_budget_ms settings of the budgets table (ms; 0: none, put first)")
    parser.add_argument("--look", default="plain", choices=LOOKS, help="scene look (default plain)")
    parser.add_argument("--params", type=Path, help="estimator YAML every table starts from (default: the defaults)")
    parser.add_argument("--n", type=int, default=6, help="images per scene")
    parser.add_argument("--rounds", type=int, default=2, help="passes over the images, the order turned each time")
    parser.add_argument("--part", default="sharp_bracket")
    parser.add_argument("--start-only", nargs=2, metavar=("VIEWS", "SCENE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    base = EstimatorParams.load(args.params) if args.params else EstimatorParams()
    cache = REPO / "data" / "bench"
    cache.mkdir(parents=True, exist_ok=True)
    step = step_file(args.part, cache)
    scenes = {name: latency_scene(step, cache, name, args.n, args.look) for name in args.scenes}
    paths = {views: cached_graph_path(step, cache, fibonacci_step(views), label=f"{views}views")
             for views in args.views}
    if args.start_only:  # the child process of the start table
        views, name = args.start_only
        print(start_row(paths[int(views)], *scenes[name], args.part_workers, base))
        return 0

    if "workers" in args.tables:
        print_table(["views", "scene", "workers", *(f"{s} ms" for s in STAGES[:-1]), "ms/image", "images/s",
                     "speed-up", "same poses", "CPU ms/image"], paths, scenes,
                    lambda graph, scene, images: workers_table(graph, scene, images, args.workers, args.rounds, base))
    if "parts" in args.tables:
        print_table(["views", "scene", "parts", "edges", "workers each", "ms/image", "part-images/s", "time / 1 part"],
                    paths, scenes, lambda graph, scene, images: parts_table(graph, scene, images, args.parts,
                                                                            args.part_workers, args.rounds, base))
    if "start" in args.tables:
        print(load_average())
        print("\n| views | scene | workers | setup s | first image ms | steady ms | first / steady | "
              "that image again ms | first / again | peak RSS MB |")
        print("|" + "---|" * 10)
        for views in paths:
            for name in scenes:
                child = subprocess.run([sys.executable, __file__, "--start-only", str(views), name,
                                        "--views", str(views), "--scenes", name, "--n", str(args.n),
                                        "--part", args.part, "--part-workers", str(args.part_workers),
                                        "--look", args.look, *(["--params", str(args.params)] if args.params else [])],
                                       capture_output=True, text=True, check=True)
                print(f"| {views} | {name} | {args.part_workers} {child.stdout.strip()}", flush=True)
    if "budgets" in args.tables:
        print_table(["views", "scene", "budget ms", "ms/image", "90 %", "most", "a step left out",
                     "pose as without a budget"], paths, scenes,
                    lambda graph, scene, images: budgets_table(graph, scene, images, args.budgets, args.rounds, base))
    print(load_average())
    return 0


if __name__ == "__main__":
    sys.exit(main())

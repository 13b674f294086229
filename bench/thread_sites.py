"""Where one image's CPU time goes, by the worker pool's call sites, and how well it splits.

    python bench/thread_sites.py [--scene occluded|clean] [--views 2500] [--n 6] [--rounds 2]
                                 [--workers 1] [--part sharp_bracket] [--look plain|varied]

Runs ``Estimator.estimate`` over bench/latency.py's images with every ``WorkerPool.map`` call
timed: per call site (the function that called ``map`` and its caller), the CPU time of its
chunks (``time.thread_time``, which waiting for a core does not inflate, so the table holds on
a shared machine), the calls and chunks per image, and the time two threads would take on
those chunks (each chunk's time, handed in order to the thread free first: the makespan)
against half their sum; and the caller's CPU time outside the pool (Python that a second
worker cannot share). The numbers are CPU ms per image (means).

The pool's chunks are timed by wrapping ``WorkerPool.map`` in this process; nothing else
changes. A ``map`` inside a chunk (the pre-filter of a tetrad cluster, run serially in its
task) counts as its chunk's time, at the outer site.
"""
from __future__ import annotations

import argparse
import sys
import threading
import time
import traceback
from collections import defaultdict
from pathlib import Path


REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import step_file  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from bench.latency import SCENES, latency_scene, load_average, with_workers  # noqa: E402
from brepose_ros.synthetic.scenes import LOOKS  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.online import workers  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.viewsphere import fibonacci_step  # noqa: E402


class SiteTimer:
    """Wraps ``WorkerPool.map`` to time each call's chunks by call site."""

    def __init__(self):
        self.sites: dict[str, list[float]] = defaultdict(lambda: [0, 0, 0.0, 0.0])  # calls, chunks, cpu, makespan
        self.in_pool = 0.0  # the calling thread's CPU seconds inside map
        self._map = workers.WorkerPool.map
        self._inside = threading.local()  # whether this thread runs a timed map's chunk

    def __enter__(self) -> "SiteTimer":
        timer = self

        def timed_map(pool, function, chunks):
            if getattr(timer._inside, "chunk", False):
                return timer._map(pool, function, chunks)
            seconds = [0.0] * len(chunks)
            lock = threading.Lock()

            def timed(i):
                timer._inside.chunk = True
                start = time.thread_time()
                try:
                    result = function(chunks[i])
                finally:
                    timer._inside.chunk = False
                with lock:
                    seconds[i] = time.thread_time() - start
                return result

            start = time.thread_time()
            results = timer._map(pool, timed, range(len(chunks)))
            timer.in_pool += time.thread_time() - start
            caller, site = traceback.extract_stack(limit=3)[:2]
            record = timer.sites[f"{Path(site.filename).stem}.{site.name} <- {caller.name}"]
            record[0] += 1
            record[1] += len(chunks)
            record[2] += sum(seconds)
            record[3] += makespan(seconds, 2)
            return results

        workers.WorkerPool.map = timed_map
        return self

    def __exit__(self, *exc) -> None:
        workers.WorkerPool.map = self._map


def makespan(seconds: list[float], threads: int) -> float:
    """The time ``threads`` threads take on chunks of these times, each chunk taken in order
    by the thread free first (as ``WorkerPool.map`` hands them out)."""
    ends = [0.0] * threads
    for s in seconds:
        ends[ends.index(min(ends))] += s
    return max(ends)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="occluded", choices=list(SCENES))
    parser.add_argument("--views", type=int, default=2500)
    parser.add_argument("--workers", type=int, default=1, help="matching.workers while timing")
    parser.add_argument("--n", type=int, default=6, help="images")
    parser.add_argument("--rounds", type=int, default=2, help="passes over the images")
    parser.add_argument("--part", default="sharp_bracket")
    parser.add_argument("--look", default="plain", choices=LOOKS, help="scene look (bench/latency.py)")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    step = step_file(args.part, cache)
    scene, images = latency_scene(step, cache, args.scene, args.n, args.look)
    graph = AspectGraph.load(cached_graph_path(step, cache, fibonacci_step(args.views), label=f"{args.views}views"))
    estimator = Estimator(graph, with_workers(args.workers))
    estimator.estimate(images[0], scene.camera)  # the first image is not the steady state
    print(load_average())
    caller = 0.0
    with SiteTimer() as timer:
        for _ in range(args.rounds):
            for image in images:
                start = time.thread_time()
                estimator.estimate(image, scene.camera)
                caller += time.thread_time() - start
    estimator.close()
    print(load_average())
    count = args.rounds * len(images)
    print(f"\n{args.part}, {graph.n_views} views, {args.scene}, {count} estimates, workers {args.workers}")
    print("\n| call site | CPU ms | calls | chunks / call | 2 threads ms | half the CPU ms |")
    print("|---|---|---|---|---|---|")
    for site, (calls, chunks, cpu, span) in sorted(timer.sites.items(), key=lambda kv: -kv[1][2]):
        print(f"| {site} | {1000 * cpu / count:.1f} | {calls / count:.1f} | {chunks / calls:.1f} | "
              f"{1000 * span / count:.1f} | {500 * cpu / count:.1f} |")
    total = sum(cpu for _, _, cpu, _ in timer.sites.values())
    spans = sum(span for _, _, _, span in timer.sites.values())
    outside = caller - timer.in_pool
    print(f"| **the pool, all sites** | {1000 * total / count:.1f} | | | {1000 * spans / count:.1f} | "
          f"{500 * total / count:.1f} |")
    print(f"| **the caller outside the pool** | {1000 * outside / count:.1f} | | | {1000 * outside / count:.1f} | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

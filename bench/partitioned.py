"""Parts spread over K estimator processes (launch_free_scripts/run_partitioned.py) against
one process with every part: images/s and latency until every part has answered.

    python bench/partitioned.py [--processes 1 2] [--parts 2] [--views 2500] [--scene occluded] [--n 6]
                                [--repeats 2] [--workers 1]

The same graph is loaded once per part (parts of equal cost). Images of the latency
scene go out lock-step from play_bag.py (reliable, the next image once every part has
answered the last) on a random ROS_DOMAIN_ID; the settings alternate run by run.
``--workers`` is each estimator's ``matching.workers``.
"""
from __future__ import annotations

import argparse
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path


REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import step_file  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from bench.latency import SCENES, latency_scene  # noqa: E402
from brepose_ros.ros.bags import write_bag  # noqa: E402
from brepose_ros.viewsphere import fibonacci_step  # noqa: E402

SCRIPTS = REPO / "launch_free_scripts"


def ros_env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("ROS_AUTOMATIC_DISCOVERY_RANGE",)}
    return {**env, "ROS_DOMAIN_ID": str(random.randint(100, 200))}


def run(processes: int, graphs: list[Path], bag: Path, workers: int, folder: Path) -> tuple[float, float]:
    """images/s and median latency of one lock-step replay into ``processes`` processes."""
    env = ros_env()
    params = folder / "params.yaml"
    params.write_text(f"estimator:\n  ros__parameters:\n    debug_image: false\n    matching:\n"
                      f"      workers: {workers}\n")
    log = folder / f"nodes_{processes}.log"
    nodes = subprocess.Popen([sys.executable, str(SCRIPTS / "run_partitioned.py"), "--processes", str(processes),
                              "--graphs", *map(str, graphs), "--params-file", str(params)],
                             stdout=log.open("w"), stderr=subprocess.STDOUT, env=env)
    try:
        deadline = time.monotonic() + 120
        while log.read_text().count("estimating") < processes:
            if nodes.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(log.read_text())
            time.sleep(0.2)
        played = subprocess.run([sys.executable, str(SCRIPTS / "play_bag.py"), str(bag), "--reliability", "reliable",
                                 "--nodes", str(processes), "--statuses", str(len(graphs)), "--timeout", "60"],
                                capture_output=True, text=True, env=env, check=True)
    finally:
        nodes.send_signal(signal.SIGINT)
        nodes.wait(timeout=30)
    found = re.search(r"answered (\d+) \(([\d.]+)/s\), median latency (\d+) ms", played.stdout)
    if found is None:
        raise RuntimeError(played.stdout + played.stderr)
    return float(found.group(2)), float(found.group(3))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--processes", type=int, nargs="*", default=[1, 2])
    parser.add_argument("--parts", type=int, default=2)
    parser.add_argument("--views", type=int, default=2500)
    parser.add_argument("--scene", default="occluded", choices=list(SCENES))
    parser.add_argument("--n", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--part", default="sharp_bracket")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    step = step_file(args.part, cache)
    graph = cached_graph_path(step, cache, fibonacci_step(args.views), label=f"{args.views}views")
    scene, images = latency_scene(step, cache, args.scene, args.n)
    with tempfile.TemporaryDirectory(prefix="brepose_partitioned_bench_") as tmp:
        folder = Path(tmp)
        graphs = []
        for k in range(args.parts):
            graphs.append(folder / f"part{k}.brepose.npz")
            shutil.copy(graph, graphs[-1])
        write_bag(folder / "bag", images, scene.camera, rate=10.0)
        results = {k: [] for k in args.processes}
        for r in range(args.repeats):
            order = args.processes if r % 2 == 0 else args.processes[::-1]
            for k in order:
                results[k].append(run(k, graphs, folder / "bag", args.workers, folder))
                print(f"  run {r}: {k} process(es): {results[k][-1][0]:.2f} images/s, "
                      f"median latency {results[k][-1][1]:.0f} ms", file=sys.stderr, flush=True)
    base = sum(rate for rate, _ in results[args.processes[0]])
    print(f"\n| processes | parts | workers each | images/s (every part answered) | median latency ms | "
          f"throughput / {args.processes[0]} process |")
    print("|---|---|---|---|---|---|")
    for k in args.processes:
        rates = [rate for rate, _ in results[k]]
        latencies = sorted(lat for _, lat in results[k])
        print(f"| {k} | {args.parts} | {args.workers} | {sum(rates) / len(rates):.2f} | "
              f"{latencies[len(latencies) // 2]:.0f} | {sum(rates) / base:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Where one image's work holds the GIL: per stage, the wall time and the share of it spent
holding the GIL, sampled by py-spy, and what that share allows two threads at best.

    python bench/gil_profile.py [--views 2500] [--scenes clean occluded] [--n 6] [--repeats 4]
                                [--workers 1] [--rate 250]

The estimator runs the scene's images ``--repeats`` times in a child process, sampled by
two py-spy processes at once: ``py-spy record`` (every sample of a running thread) and
``py-spy record --gil`` (only samples of the thread holding the GIL). A stage's GIL share
is the ratio of its two sample counts. A thread waiting for a core counts as running in
both, so the share hardly depends on how busy the machine is, unlike the wall time.

The bound: a stage holding the GIL a share ``s`` of its time runs on 2 threads at best in
``s + (1 - s) / 2`` of its time (Amdahl, with the GIL-free rest split perfectly and the
GIL-holding rest serial); the total's bound sums the stages. "in pool chunks" is the share
that runs inside ``WorkerPool.map`` today, and the last row the bound when only that share
is split. py-spy is not a dependency
of the project: ``pip install py-spy`` into the venv to run this.
"""
from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

#: (stage, step, function, file): a sample belongs to the first stage and the deepest step
#: whose function is on its stack; steps are listed under their stage
STEPS = [
    ("edges", "gray, blur, Sobel", "to_gray", "image_edges.py"),
    ("edges", "gray, blur, Sobel", "gradients", "image_edges.py"),
    ("edges", "gray, blur, Sobel", "colour_gradients", "image_edges.py"),
    ("edges", "Canny", "canny_from_gradients", "image_edges.py"),
    ("edges", "Hough", "hough_segments", "image_edges.py"),
    ("edges", "merge", "merge_segments", "image_edges.py"),
    ("edges", "refit to pixels", "refine_segments", "image_edges.py"),
    ("edges", "edge evidence", "__init__", "scoring.py"),
    ("edges", "undistort", "undistort", "camera.py"),
    ("regions", "regions", "region_groups", "regions.py"),
    ("regions", "regions", "normalised_region", "regions.py"),
    ("prefilter", "rotation candidates", "rotation_candidates", "prefilter.py"),
    ("prefilter", "chamfer gather", "_scores_of", "prefilter.py"),
    ("matching", "compiled align (Kuhn-Munkres, similarity, 2D ICP, coverage)", "align", "matching.py"),
    ("refinement", "line rounds", "refine", "refinement.py"),
    ("refinement", "Gauss-Newton", "refine_poses", "refinement.py"),
    ("refinement", "edge-pixel pairing", "align_on_edges", "refinement.py"),
    ("refinement", "score", "pose_scores", "scoring.py"),
    ("refinement", "twins", "check_twins", "symmetry.py"),
    ("refinement", "error ratio", "edge_pairs", "scoring.py"),
    ("search", "response and chance maps", "of", "search.py"),
    ("search", "response and chance maps", "chances", "search.py"),
    ("search", "coarse kernel", "run", "search.py"),  # the chunk calling the numba kernel
    ("search", "kept templates", "best", "search.py"),
    ("matching", "seeds' windows", "_seed_jobs", "hypotheses.py"),
]
#: the stage of a sample: the first function on its stack inside ``Estimator.estimate`` named
#: here, by py-spy's qualified name (``Class.method``) before the plain one
STAGE_OF = {"detect": "edges", "detect_edges": "edges", "of": "edges", "region_groups": "regions",
            "normalised_region": "regions", "shortlist": "prefilter", "match": "matching", "at_seeds": "matching",
            "verify": "refinement", "realign": "refinement", "best": "refinement", "check_twins": "refinement",
            "edge_pairs": "refinement", "pose_shares": "refinement", "hypotheses": "search", "coarse": "search",
            "TemplateSearch.best": "search", "places": "search"}
STAGE_ORDER = ["edges", "regions", "prefilter", "matching", "refinement", "search", "other"]
FRAME = re.compile(r"^(?P<function>.+?) \((?P<file>[^():]+)(?::\d+)?\)$")


def child(args) -> None:
    """Run the estimator over the images ``repeats`` times (what py-spy samples)."""

    from bench.accuracy import step_file
    from bench.graphs import cached_graph_path
    from bench.latency import latency_scene, with_workers
    from brepose_ros.aspect_graph import AspectGraph
    from brepose_ros.online.estimator import Estimator
    from brepose_ros.viewsphere import fibonacci_step

    cache = REPO / "data" / "bench"
    step = step_file(args.part, cache)
    scene, images = latency_scene(step, cache, args.child, args.n)
    graph = AspectGraph.load(cached_graph_path(step, cache, fibonacci_step(args.views[0]),
                                               label=f"{args.views[0]}views"))
    estimator = Estimator(graph, with_workers(args.workers))
    estimator.estimate(images[0], scene.camera)
    print("ready", flush=True)
    sys.stdin.readline()  # py-spy has attached
    for _ in range(args.repeats):
        for image in images:
            estimator.estimate(image, scene.camera)
    estimator.close()


def sampled(args, scene: str) -> tuple[dict[tuple[str, str], int], dict[tuple[str, str], int]]:
    """{(stage, step): samples inside ``Estimator.estimate``} of one child run, sampled by
    two py-spy processes at once: all samples of running threads, and those holding the GIL."""
    spy = shutil.which("py-spy") or str(Path(sys.executable).parent / "py-spy")
    with tempfile.TemporaryDirectory() as folder:
        # attached to the running child: the venv's start-up re-executes the interpreter,
        # which a py-spy that started the program loses track of
        program = subprocess.Popen([sys.executable, __file__, "--child", scene, "--views", str(args.views[0]),
                                    "--n", str(args.n), "--repeats", str(args.repeats), "--workers",
                                    str(args.workers), "--part", args.part],
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        while program.stdout.readline().strip() != "ready":
            if program.poll() is not None:
                raise SystemExit(f"error: the estimator's process ended with status {program.returncode}")
        outputs = [Path(folder) / "active.txt", Path(folder) / "gil.txt"]
        spies = [subprocess.Popen([spy, "record", "--format", "raw", "--nolineno", "--nonblocking", "-r",
                                   str(args.rate), "-o", str(out), *(["--gil"] if out.stem == "gil" else []),
                                   "-p", str(program.pid)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                 for out in outputs]
        time.sleep(2.0)
        program.stdin.write("go\n")
        program.stdin.flush()
        program.wait()
        for spy_process in spies:
            spy_process.wait()
        return tuple(stage_counts(out.read_text().splitlines()) for out in outputs)


def stage_counts(lines: list[str]) -> dict[tuple[str, str, bool], int]:
    """{(stage, step, split): samples} of py-spy's raw output, inside ``Estimator.estimate``
    only; ``split`` when the sample ran in a chunk of ``WorkerPool.map``."""
    counts: dict[tuple[str, str], int] = defaultdict(int)
    for line in lines:
        stack, _, count = line.rpartition(" ")
        frames = [m.groupdict() for m in map(FRAME.match, stack.split(";")) if m]
        for f in frames:  # py-spy names methods Class.method
            f["qualified"], f["function"] = f["function"], f["function"].rpartition(".")[2]
        names = [f["function"] for f in frames]
        if "estimate" not in names:
            continue  # loading, warming up
        inside = frames[names.index("estimate") + 1:]
        stage = next((STAGE_OF.get(f["qualified"], STAGE_OF.get(f["function"])) for f in inside
                      if f["qualified"] in STAGE_OF or f["function"] in STAGE_OF), "other")
        step = "rest"
        for f in inside:
            for step_stage, label, function, file in STEPS:
                if step_stage == stage and f["function"] == function and f["file"].endswith(file):
                    step = label
        split = any(f["function"] == "map" and f["file"].endswith("workers.py") for f in inside)
        counts[(stage, step, split)] += int(count)
    return counts


def two_thread_time(held: float, free: float) -> float:
    """Amdahl: the GIL-holding time stays serial, the GIL-free time halves."""
    return held + free / 2


def table(args, scene: str) -> list[str]:
    active, held = sampled(args, scene)
    scale = 1000.0 / args.rate / (args.n * args.repeats)  # samples -> ms per image

    def sums(keys) -> tuple[float, float, float]:
        """ms per image of the keys' samples, of those holding the GIL, of those split."""
        return (scale * sum(active[k] for k in keys), scale * sum(min(held.get(k, 0), active[k]) for k in keys),
                scale * sum(active[k] for k in keys if k[2]))

    def row(label: str, keys) -> str:
        ms, gil, split = sums(keys)
        return (f"| {label} | {ms:.1f} | {100 * gil / ms:.0f} % | {100 * split / ms:.0f} % | "
                f"{ms / two_thread_time(gil, ms - gil):.2f} |")

    rows = []
    for stage in STAGE_ORDER:
        keys = [k for k in active if k[0] == stage]
        if not keys:
            continue
        rows.append(row(f"{scene} **{stage}**", keys))
        steps = sorted({k[1] for k in keys}, key=lambda step: -sum(active[k] for k in keys if k[1] == step))
        for step in steps:
            step_keys = [k for k in keys if k[1] == step]
            if sums(step_keys)[0] >= 0.3:
                rows.append(row(f"&nbsp;&nbsp;{step}", step_keys))
    rows.append(row(f"{scene} **total**", list(active)))
    # today's bound: only the chunks of WorkerPool.map run on two threads
    ms, gil, split = sums(list(active))
    split_gil = scale * sum(min(held.get(k, 0), active[k]) for k in active if k[2])
    today = (ms - split) + two_thread_time(split_gil, split - split_gil)
    rows.append(f"| {scene} bound with today's split | | | | {ms / today:.2f} |")
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--views", type=int, nargs=1, default=[2500])
    parser.add_argument("--scenes", nargs="*", default=["clean", "occluded"])
    parser.add_argument("--n", type=int, default=6, help="images per scene")
    parser.add_argument("--repeats", type=int, default=4, help="passes over the images per sampled run")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--rate", type=int, default=250, help="samples per second")
    parser.add_argument("--part", default="sharp_bracket")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        child(args)
        return 0
    print("| stage / step | ms per image (sampled) | GIL held | in pool chunks | 2-thread bound |")
    print("|---|---|---|---|---|")
    for scene in args.scenes:
        for row in table(args, scene):
            print(row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

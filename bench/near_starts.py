"""Does the hypothesis refinement pull a near start in? Starts made from the truth of the
cached bench scenes, refined as ``PoseRefiner.verify`` refines a hypothesis, with and
without the alignment on edge pixels, then (``--climb``) climbed over the neighbouring
views as ``PoseRefiner.best`` climbs a start, then polished.

    python bench/near_starts.py [--n 6] [--parts sharp_bracket ...] [--conditions clean clutter] \
        [--angles 5 10 15] [--offset 0.05] [--reps 2] [--climb]

Per image and angle, ``--reps`` starts: the truth turned by the angle about a random axis
through the part's centre, the centre moved by ``--offset`` part diameters in a random
direction (the same starts for both settings; seeded by part, condition and image). A start
counts as converged when its pose is a success (CONVENTIONS.md: rotation < 5 degrees,
translation < 5 % of the diameter, up to exact symmetry), after the rounds and after the
polish. The two settings alternate start by start, so their times (milliseconds per start,
scoring included) compare within the run. ``--angles 0 --offset 0 --reps 1`` refines and
polishes the truth itself.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from bench.accuracy import TUNING, add_scene_arguments, bench_steps, cached_frames, graph_and_model  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.metrics import pose_errors  # noqa: E402
from brepose_ros.geometry import rotation_about  # noqa: E402
from brepose_ros.online.refinement import Candidate, PoseRefiner, hypothesis_rounds  # noqa: E402
from brepose_ros.online.workers import SERIAL  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402

SETTINGS = {"lines only": False, "aligned": True}


def near_start(R, t, graph: AspectGraph, angle_deg: float, offset: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """The pose turned by ``angle_deg`` about a random axis through the part's centre, the
    centre moved ``offset`` diameters in a random direction."""
    axis, shift = rng.normal(size=3), rng.normal(size=3)
    R_start = rotation_about(axis / np.linalg.norm(axis), np.radians(angle_deg)) @ R
    center = R @ graph.model_center + t + offset * graph.model_diameter * shift / np.linalg.norm(shift)
    return R_start, center - R_start @ graph.model_center


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=6, parts=TUNING, conditions=["clean", "clutter"], start=True)
    parser.add_argument("--angles", nargs="*", type=float, default=[5.0, 10.0, 15.0])
    parser.add_argument("--offset", type=float, default=0.05, help="centre offset, part diameters")
    parser.add_argument("--reps", type=int, default=2, help="starts per image and angle")
    parser.add_argument("--climb", action="store_true", help="climb each refined start before its polish")
    args = parser.parse_args(argv)
    params = EstimatorParams()
    p = params.pose
    cache = REPO / "data" / "bench"
    # setting -> angle -> [converged after the rounds, after the polish, starts, seconds]
    tally = {s: {a: [0, 0, 0, 0.0] for a in args.angles} for s in SETTINGS}
    for name, step in bench_steps(args.parts, cache).items():
        graph, model = graph_and_model(step, cache)
        refiner = PoseRefiner(graph)
        for condition in args.conditions:
            for i, entry, _, frame in cached_frames(cache, name, condition, params, args.start, args.n):
                rng = np.random.default_rng([i, *map(ord, name + condition)])
                row = []
                for angle in args.angles:
                    for _ in range(args.reps):
                        R0, t0 = near_start(entry.R, entry.t, graph, angle, args.offset, rng)
                        for setting, align in SETTINGS.items():
                            clock = time.perf_counter()
                            R, t, score = refiner.refined_scores(R0[None], t0[None], frame, p,
                                                                 hypothesis_rounds(p.refine_iterations), SERIAL,
                                                                 align=align)
                            seconds = time.perf_counter() - clock
                            refined = Candidate(float(score[0]), R[0], t[0], None)
                            polished = refiner.polish(refiner.climb(refined, frame, p) if args.climb else refined,
                                                      frame, p)
                            ok = [pose_errors(R_k, t_k, entry.R, entry.t, model, graph).success_sym
                                  for R_k, t_k in ((R[0], t[0]), (polished.R, polished.t))]
                            counts = tally[setting][angle]
                            counts[0] += ok[0]
                            counts[1] += ok[1]
                            counts[2] += 1
                            counts[3] += seconds
                            row.append(f"{'+' if ok[1] else '-'}{polished.score:.2f}")
                print(f"{name} {condition} {i}: " + " ".join(row), flush=True)
    print(f"\nconverged after the rounds / after the{' climb and the' if args.climb else ''} polish, of the starts; "
          "ms per start (rounds, scoring included)\n")
    print("| setting | " + " | ".join(f"{a:g} deg" for a in args.angles) + " | ms |")
    print("|---|" + "---|" * (len(args.angles) + 1))
    for setting, rows in tally.items():
        starts = sum(c[2] for c in rows.values())
        print(f"| {setting} | " + " | ".join(f"{c[0]} / {c[1]} of {c[2]}" for c in rows.values())
              + f" | {1000 * sum(c[3] for c in rows.values()) / max(starts, 1):.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

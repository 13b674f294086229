"""Does the image's edges running on past the ends of a pose's model edges tell a pose at the
wrong depth from the truth?

    python bench/run_on.py [--n 8] [--parts sharp_bracket ...] [--conditions clean clutter] [--label NAME] \
        [group.key=value ...]

Per image of bench/accuracy.py's cached scenes (varied look, seed 100, 5-degree graphs) the
estimator's path is replayed (bench/choice_losses.py's ``candidates_and_best``, then the twin
check). For the final pose, the truth refined like a hypothesis and polished
(``refined_truth``) and the refined candidates, the *run-on* (``scoring.Shares.run_on``): of
the probe points beyond the ends of the pose's visible model edges, along them and off every
other model edge, the share a like edge confirms beyond chance; and the score with and
without its factor (``EdgeEvidence.RUN_ON_WEIGHT``: 0 measures the estimator without it).

A pose is *right* (success up to the part's exact symmetries), *near* (within 15 degrees and
10 % of the diameter, hypothesis_recall's ``near_truth``), or wrong *far* / *near-depth* (its
model centre at least 10 % farther / nearer than the truth's) or *at depth*. Printed: every
wrong final pose against its image's refined truth, and per kind of pose (finals and
candidates) the quartiles of the run-on; per-pose records go to
data/bench/results/run_on_LABEL.json.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from bench.accuracy import (TUNING, add_scene_arguments, bench_steps, cached_frames, graph_and_model,  # noqa: E402
                            overridden_params, part_set)
from bench.choice_losses import candidates_and_best  # noqa: E402
from bench.hypothesis_recall import near_truth  # noqa: E402
from bench.occlusion_diagnosis import refined_truth  # noqa: E402
from brepose_ros.evaluation.metrics import pose_errors  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.scoring import EdgeEvidence, pose_shares  # noqa: E402
from brepose_ros.online.symmetry import check_twins  # noqa: E402

#: a wrong pose's centre this much farther or nearer than the truth's is at another depth
DEPTH_SAME = 0.1


def kind(pose, entry, graph, model) -> str:
    if pose_errors(pose.R, pose.t, entry.R, entry.t, model, graph).success_sym:
        return "right"
    if near_truth(pose.R, pose.t, entry, graph):
        return "near"
    depth = depth_ratio(pose, entry, graph)
    return "far" if depth >= 1 + DEPTH_SAME else "nearer" if depth <= 1 - DEPTH_SAME else "at depth"


def depth_ratio(pose, entry, graph) -> float:
    return float(np.linalg.norm(pose.R @ graph.model_center + pose.t)
                 / np.linalg.norm(entry.R @ graph.model_center + entry.t))


def measured(pose, entry, graph, model, frame, p) -> dict:
    """The pose's kind, score, depth ratio and run-on, and its score without the run-on's factor."""
    shares = pose_shares(graph, pose.R, pose.t, frame, p.pose)[0]
    factor = max(1.0 - EdgeEvidence.RUN_ON_WEIGHT * shares.run_on, 1e-12)
    return {"kind": kind(pose, entry, graph, model), "score": float(pose.score), "plain": shares.score / factor,
            "depth": depth_ratio(pose, entry, graph), "run_on": shares.run_on}


def quartiles(values) -> str:
    if not values:
        return "-"
    q = np.percentile(values, [25, 50, 75])
    return f"{q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f} ({len(values)})"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=8, parts=TUNING, conditions=["clean", "clutter"])
    parser.add_argument("--label", default="default")
    parser.add_argument("overrides", nargs="*", help="flat parameters, e.g. pose.climb_candidates=4")
    args = parser.parse_args(argv)
    params = overridden_params(args.overrides)
    cache = REPO / "data" / "bench"
    records = []
    print("| part | condition | image | final kind | depth | score final / truth | without the run-on | "
          "run-on final / truth |")
    print("|---|---|---|---|---|---|---|---|")
    for name, step in bench_steps(args.parts, cache).items():
        graph, model = graph_and_model(step, cache)
        estimator = Estimator(graph, params)
        for condition in args.conditions:
            for i, entry, _, frame in cached_frames(cache, name, condition, params, 0, args.n):
                candidates, chosen = candidates_and_best(estimator, frame, params)
                if chosen is None:
                    continue
                final = check_twins(chosen, graph, estimator._refiner, frame, params.pose)[0]
                truth = refined_truth(estimator, frame, entry)
                record = {"part": name, "set": part_set(name), "condition": condition, "image": i,
                          "final": measured(final, entry, graph, model, frame, params),
                          "truth": measured(truth, entry, graph, model, frame, params),
                          "candidates": [measured(c, entry, graph, model, frame, params) for c in candidates]}
                records.append(record)
                f, t = record["final"], record["truth"]
                if f["kind"] != "right":
                    print(f"| {name} | {condition} | {i} | {f['kind']} | {f['depth']:.2f} | "
                          f"{f['score']:.3f} / {t['score']:.3f} | {f['plain']:.3f} / {t['plain']:.3f} | "
                          f"{f['run_on']:.2f} / {t['run_on']:.2f} |", flush=True)
        estimator.close()
    print("\nrun-on: quartiles (count) per kind of pose")
    print("| set | poses | right | near | far | nearer | at depth | truth refined |")
    print("|---|---|---|---|---|---|---|---|")
    for s in sorted({r["set"] for r in records}):
        mine = [r for r in records if r["set"] == s]
        for label, poses in (("final", [r["final"] for r in mine]),
                             ("candidates", [c for r in mine for c in r["candidates"]])):
            cells = [quartiles([q["run_on"] for q in poses if q["kind"] == kd])
                     for kd in ("right", "near", "far", "nearer", "at depth")]
            print(f"| {s} | {label} | " + " | ".join(cells) + " | "
                  + quartiles([r["truth"]["run_on"] for r in mine]) + " |")
    out = cache / "results" / f"run_on_{args.label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(records, default=float) + "\n")
    print(f"\nwrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

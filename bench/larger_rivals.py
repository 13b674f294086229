"""The larger-pose check image by image: the pose it starts from, the larger rival it finds,
and which of the two the score and the evidence against chance prefer.

    python bench/larger_rivals.py [--n 16] [--start 64] [--parts sharp_bracket ...]
                                  [--conditions clean clutter occl30+clutter] [--label NAME] [--plot PNG]

For each part, condition and image of bench/accuracy.py's cached scenes, the estimator with
default parameters; where the larger check runs (``online/larger.py``: the pose scores below
``search.enough_score``), the pose and the rival ``larger_rival`` finds are recorded with
their scores, their evidence against chance (``scoring.pose_surprises``, nats) and whether
each is right (success up to the part's exact symmetries). Printed: for the images where one
of the two is right, how often the score alone and the check's rule (``prefers_rival``) take
the right one. ``--plot`` draws the rival's score and evidence against the pose's, right
rivals against right poses, with the rule's region. Records go to
data/bench/results/larger_rivals_LABEL.json.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import PARTS, add_scene_arguments, bench_steps, distractor_meshes, graph_and_model, scene  # noqa: E402
from brepose_ros.evaluation.figures import pyplot, save_figure  # noqa: E402
from brepose_ros.evaluation.metrics import pose_errors  # noqa: E402
from brepose_ros.online import estimator as estimator_module  # noqa: E402
from brepose_ros.online import larger  # noqa: E402
from brepose_ros.online.scoring import pose_surprises  # noqa: E402


class RecordedCheck:
    """``larger.larger_pose`` as the estimator calls it, keeping the pose and rival it saw."""

    def __init__(self):
        self.seen: list[tuple] = []

    def __call__(self, best, graph, frame, p, search, hypotheses, refiner, pool=larger.SERIAL):
        rival = larger.larger_rival(best, graph, frame, p, search, hypotheses, refiner, pool)
        if rival is None:
            self.seen.append((best, None, None, False))
            return best
        surprises = pose_surprises(graph, np.array([best.R, rival.R]), np.array([best.t, rival.t]), frame, p.pose)
        taken = larger.prefers_rival(best, rival, graph, frame, p)
        self.seen.append((best, rival, surprises, taken))
        return rival if taken else best


def plot(records: list[dict], path: Path) -> None:
    """Rival against pose: score ratio across, evidence ratio up, where one of the two is right."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    for right, colour, label in (("pose", "tab:blue", "the pose right, the rival wrong"),
                                 ("rival", "tab:red", "the rival right, the pose wrong")):
        chosen = [r for r in records if r["right"] == right]
        ax.scatter([r["rival_score"] / r["score"] for r in chosen],
                   [np.log2(max(r["rival_nats"], 1.0) / max(r["nats"], 1.0)) for r in chosen],
                   s=14, c=colour, label=f"{label} ({len(chosen)})", alpha=0.7)
    ax.axvline(1.0, color="grey", lw=0.8)
    ax.axvline(larger.EVIDENCE_SCORE_SHARE, color="grey", lw=0.8, ls="--")
    ax.axhline(0.0, color="grey", lw=0.8)
    ax.fill_between([larger.EVIDENCE_SCORE_SHARE, 1.0], 0, 5, color="tab:red", alpha=0.08,
                    label="taken on its evidence")
    ax.fill_betweenx([-5, 5], 1.0, 2.0, color="tab:red", alpha=0.04, label="taken on its score")
    ax.set_xlim(0, 1.6)
    ax.set_ylim(-5, 5)
    ax.set_xlabel("rival's score / pose's score")
    ax.set_ylabel("log2 (rival's evidence / pose's evidence), nats")
    ax.set_title("The larger-pose check's rival against the pose")
    ax.legend(loc="lower right", fontsize=8)
    save_figure(fig, path, 120)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=16, parts=list(PARTS), conditions=["clean", "clutter", "occl30+clutter"],
                        start=True)
    parser.add_argument("--label", default="default")
    parser.add_argument("--plot", type=Path, help="write the scatter of rivals against poses here")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    distractors = distractor_meshes(cache)
    check = RecordedCheck()
    estimator_module.larger_pose = check
    records = []
    for name, step in bench_steps(args.parts, cache).items():
        graph, model = graph_and_model(step, cache)
        estimator = estimator_module.Estimator(graph)
        for condition in args.conditions:
            images = scene(cache, name, step, condition, range(args.start, args.start + args.n), distractors)
            for i, entry in enumerate(images.entries, start=args.start):
                check.seen.clear()
                estimator.estimate(cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED), images.camera)
                if not check.seen or check.seen[0][1] is None:
                    continue
                best, rival, surprises, taken = check.seen[0]
                best_right, rival_right = (pose_errors(c.R, c.t, entry.R, entry.t, model, graph).success_sym
                                           for c in (best, rival))
                records.append({"part": name, "condition": condition, "image": i, "score": best.score,
                                "rival_score": rival.score, "nats": float(surprises[0]),
                                "rival_nats": float(surprises[1]), "taken": bool(taken),
                                "right": ("both" if best_right and rival_right else "pose" if best_right
                                          else "rival" if rival_right else "neither")})
        estimator.close()
    print(f"{len(records)} images with a larger rival; one of the two right in "
          f"{sum(r['right'] in ('pose', 'rival') for r in records)}\n")
    print("| right | images | taken by the score | taken by the check's rule |")
    print("|---|---|---|---|")
    for right in ("pose", "rival", "both", "neither"):
        chosen = [r for r in records if r["right"] == right]
        by_score = sum(r["rival_score"] > r["score"] for r in chosen)
        print(f"| {right} | {len(chosen)} | {by_score} | {sum(r['taken'] for r in chosen)} |")
    out = cache / "results" / f"larger_rivals_{args.label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(records, indent=1) + "\n")
    if args.plot:
        plot([r for r in records if r["right"] in ("pose", "rival")], args.plot)
    print(f"\nwrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

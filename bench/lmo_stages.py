"""Which stage loses the truth of a well-visible LM-O target (issue 13): per target of the
25 photos (``bench/real_lmo.py``'s, visible >= ``WELL_VISIBLE``), on the edges the estimator
sees (``Estimator.part_frame``):

- ``sizes``: whether the true projected diameter lies within the search's sizes
  (``TemplateSearch.sizes``, half a size step either side);
- ``coarse``: the rank of the best near-truth coarse template (``search_oracle.near_templates``:
  view within 20 degrees, size within 20 %, centre within 10 % of the size) among the
  search's templates (-1: none ranked), and of the best at the true size alone;
- ``seeds``: the rank of the first near-truth seed among the ``search.seeds`` distinct best
  templates (``TemplateSearch.best``, ``search_oracle.hypothesis_near``);
- ``candidates``: the rank by score of the first refined candidate near the truth
  (``Estimator.candidates``; ``hypothesis_recall.near_truth``: 15 degrees, centre within 0.1 of
  the diameter) and its score against the best candidate's.

With a results file of ``bench/real_lmo.py`` (``--results``) each row adds the estimate's
error and score and the score of the near-truth start after the polish (``near``): where the
truth refined outscores the estimate the search missed it, else the score prefers the wrong.

    python bench/lmo_stages.py [--objects 5 8 ...] [--frames N] [--results data/bench/real_lmo/results_X.json]
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.hypothesis_recall import near_truth  # noqa: E402
from bench.real_lmo import LMO, NAMES, WELL_VISIBLE, graph_of, load_targets  # noqa: E402
from bench.search_oracle import hypothesis_near, near_templates  # noqa: E402
from brepose_ros.camera import Camera  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402


def first_rank(flags) -> int:
    """The index of the first true flag (-1: none)."""
    hits = np.flatnonzero(np.asarray(flags, bool))
    return int(hits[0]) if len(hits) else -1


def target_row(estimator: Estimator, image: np.ndarray, camera: Camera, target) -> dict:
    graph, p = estimator.graph, estimator.params
    search = estimator._search
    frame = estimator.part_frame(image, camera)
    center = target.R @ graph.model_center + target.t
    true_size = camera.focal * graph.model_diameter / np.linalg.norm(center)
    sizes = search.sizes(frame, p.search)
    half_step = np.sqrt(p.search.size_step)
    coarse = search.coarse(frame, p.search)
    near = near_templates(coarse, graph, camera, target) & (coarse.score > -1.0)
    order = np.argsort(-coarse.score)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    at_size = coarse.size_index == int(np.argmin(np.abs(np.log(sizes / true_size))))
    seeds = search.best(coarse, frame, p.search.seeds, p.search)
    candidates = sorted(estimator.candidates(frame), key=lambda c: -c.score)
    near_candidates = [near_truth(c.R, c.t, target, graph) for c in candidates]
    k = first_rank(near_candidates)
    return dict(obj=target.obj, frame=target.frame, size=true_size, low=float(sizes[0]), high=float(sizes[-1]),
                in_sizes=bool(sizes[0] / half_step <= true_size <= sizes[-1] * half_step),
                coarse=int(rank[near].min()) if near.any() else -1,
                coarse_at_size=int(rank[near & at_size].min()) if (near & at_size).any() else -1,
                best_size=float(coarse.size[order[0]]),
                seed=first_rank([hypothesis_near(graph, h, target) for h in seeds]),
                candidate=k, candidates=len(candidates),
                candidate_score=candidates[k].score if k >= 0 else float("nan"),
                best_candidate=candidates[0].score if candidates else float("nan"))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", type=int, nargs="*", default=list(NAMES), choices=list(NAMES))
    parser.add_argument("--frames", type=int, help="only the first N frames")
    parser.add_argument("--params", type=Path, help="estimator parameter YAML")
    parser.add_argument("--results", type=Path, help="bench/real_lmo.py's results of the same estimator")
    parser.add_argument("--out", type=Path, help="the rows as JSON")
    args = parser.parse_args(argv)
    params = EstimatorParams.load(args.params) if args.params else EstimatorParams()
    params = params.with_flat({"pose.min_score": 0.0, "pose.min_confidence": 0.0})
    camera = Camera.load(LMO / "camera.json")
    targets = [t for t in load_targets(LMO) if t.visible >= WELL_VISIBLE]
    frames = sorted({t.frame for t in targets})[: args.frames]
    images = {f: cv2.imread(str(LMO / "rgb" / f"{f:06d}.png"), cv2.IMREAD_COLOR) for f in frames}
    estimated = {}
    if args.results:
        estimated = {(r["obj"], r["frame"]): r for r in json.loads(args.results.read_text())}
    rows = []
    for obj in args.objects:
        estimator = Estimator(graph_of(obj, 5.0), params)
        for target in (t for t in targets if t.obj == obj and t.frame in images):
            row = target_row(estimator, images[target.frame], camera, target)
            if (obj, target.frame) in estimated:
                r = estimated[obj, target.frame]
                row |= dict(correct=r["correct"], error=r["error"], score=r["score"], near=r["near_score"],
                            near_correct=r["near_correct"])
            rows.append(row)
            print(f"{NAMES[obj]:12s} {target.frame:5d} size {row['size']:4.0f} ({row['low']:3.0f}-{row['high']:3.0f}"
                  f"{'' if row['in_sizes'] else ' OUT'}) best {row['best_size']:4.0f}  coarse {row['coarse']:5d} "
                  f"at size {row['coarse_at_size']:5d}  seed {row['seed']:4d}  candidate {row['candidate']:3d} "
                  f"of {row['candidates']:3d} ({row['candidate_score']:.2f} / {row['best_candidate']:.2f})"
                  + (f"  estimate {row['error']:.2f} d {row['score']:.2f}, near {row['near']:.2f}"
                     if "error" in row else ""), file=sys.stderr, flush=True)
        estimator.close()
    summary(rows)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1))
    return 0


def summary(rows: list[dict]) -> None:
    """Per object: targets, search sizes holding the truth, a near coarse template ranked, a
    near seed, a near candidate, the estimate right, and among the wrong the truth refined
    outscoring the estimate (a search miss) or not (the score)."""
    print("| object | targets | in sizes | near template ranked | near seed | near candidate | first candidate "
          "near | right | wrong: near truth outscores | wrong: score prefers it |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    by = defaultdict(list)
    for r in rows:
        by[NAMES[r["obj"]]].append(r)
    for name, rs in [*by.items(), ("all", rows)]:
        wrong = [r for r in rs if "correct" in r and not r["correct"]]
        print(f"| {name} | {len(rs)} | {sum(r['in_sizes'] for r in rs)} | {sum(r['coarse'] >= 0 for r in rs)} | "
              f"{sum(r['seed'] >= 0 for r in rs)} | {sum(r['candidate'] >= 0 for r in rs)} | "
              f"{sum(r['candidate'] == 0 for r in rs)} | {sum(r.get('correct', False) for r in rs)} | "
              f"{sum(r['near'] > r['score'] for r in wrong)} | {sum(r['near'] <= r['score'] for r in wrong)} |")


if __name__ == "__main__":
    sys.exit(main())

"""Where the estimator loses a partly hidden part: per image of the cached bench scenes,
each stage's view of the truth, and the stage that loses it.

    python bench/occlusion_diagnosis.py [--n 8] [--parts sharp_bracket ...] \
        [--conditions occl30+clutter ...] [group.key=value ...]

Per image: the truth's score as it is and refined like a hypothesis, then polished
(``truth`` / ``refined``, against ``pose.min_score`` and the chosen pose's score), the
score's parts at the refined truth (confirmed / explained / significance), the rank among
all coarse templates of the best near-truth one (``search_oracle``), whether a seed of
the ``seeded`` stage and a place of the ``windows`` stage lie near the truth (a rank beyond
the kernel's ranked templates shows as -1, see ``search_oracle``), whether a
refined candidate does (recall, bench/hypothesis_recall.py's definition), and the final
pose. The loss, the first that applies:

Right is CONVENTIONS.md success up to the part's exact symmetries throughout (as *near*
is), the final pose is the estimator's (finalists, rival and twin checks), and found is the
``pose.min_score`` floor alone (the confidence floor is not applied).

- ``ok``: the final pose is right and found;
- ``wall``: even the refined truth scores below ``pose.min_score``;
- ``depth``: no candidate is near the truth, but one is turned like it (within
  ``NEAR_DEG``) with its centre on the truth's line of sight (within ``NEAR_CENTRE``
  diameters across it) at another depth: a wrong size of the right view;
- ``coarse``: no seed and no place near the truth, and no candidate near it;
- ``matching``: a seed or a place is near the truth but no candidate is (the matching or
  the refinement of the hypotheses lost it);
- ``drift``: a candidate is near the truth, but the best near one, climbed and polished, is
  not right (the refinement does not reach the truth from it);
- ``choice``: a near candidate climbs to a right pose, but the final pose is another
  (a wrong pose outscores it);
- ``low``: the final pose is right but scores below ``pose.min_score``.

Beside the losses, two ceilings per set and condition: the images a **perfect search** would
get right (the refined truth among the candidates, the score choosing: right where the
refined truth is right, found and outscores the final pose) and a **perfect search and
choice** (right wherever the refined truth is right and found): what the score allows.

Columns besides: ``depth x`` is the final pose's centre distance over the truth's (a wrong
size when it is 10 % or more off 1), ``near climbed`` the best near candidate climbed and
polished (its score, y if right), ``truth > final`` whether the refined truth outscores the
final pose.
"""
from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from bench.accuracy import (TUNING, add_scene_arguments, bench_steps, cached_frames, graph_and_model,  # noqa: E402
                            overridden_params, part_set)
from bench.hypothesis_recall import NEAR_CENTRE, NEAR_DEG, chosen_pose, near_truth  # noqa: E402
from bench.search_oracle import hypothesis_near, near_templates  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, pose_errors, symmetric_truth  # noqa: E402
from brepose_ros.geometry import rotation_angle_deg  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.refinement import Candidate, hypothesis_rounds  # noqa: E402
from brepose_ros.online.scoring import pose_scores, pose_shares  # noqa: E402
from brepose_ros.online.symmetry import check_twins  # noqa: E402
from brepose_ros.online.workers import SERIAL  # noqa: E402

LOSSES = ("ok", "wall", "depth", "coarse", "matching", "drift", "choice", "low")
#: the ceilings tallied beside the losses (``ceilings``)
CEILINGS = ("perfect search", "perfect search and choice")


def refined_truth(estimator: Estimator, frame: Frame, entry) -> Candidate:
    """The true pose refined like a hypothesis, then polished if that scores higher: the best
    the estimator could report if its search started at the truth."""
    refiner, p = estimator._refiner, estimator.params.pose
    R1, t1, s1 = refiner.refined_scores(entry.R[None].astype(float), entry.t[None].astype(float), frame, p,
                                        hypothesis_rounds(p.refine_iterations), SERIAL)
    polished = refiner.polish(Candidate(float(s1[0]), R1[0], t1[0], None), frame, p)
    return polished if polished.score >= s1[0] else Candidate(float(s1[0]), R1[0], t1[0], None)


def turned_like_truth(R, t, entry, graph) -> bool:
    """Turned like the truth (symmetry aware) with its centre on the truth's line of sight,
    at any depth: a pose a scan along that line could carry to the truth."""
    R_true, t_true = symmetric_truth(R, entry.R, entry.t, graph)
    truth, centre = R_true @ graph.model_center + t_true, R @ graph.model_center + t
    across = np.linalg.norm(truth[:2] / truth[2] - centre[:2] / centre[2]) * truth[2]
    return bool(rotation_angle_deg(R, R_true) < NEAR_DEG and centre[2] > 0
                and across < NEAR_CENTRE * graph.model_diameter)


def depth_ratio(pose, entry, graph) -> float:
    """The pose's model centre distance over the truth's."""
    return float(np.linalg.norm(pose.R @ graph.model_center + pose.t)
                 / np.linalg.norm(entry.R @ graph.model_center + entry.t))


def diagnose(estimator: Estimator, frame: Frame, entry, model: ModelPoints) -> dict:
    g, p, refiner, search = estimator.graph, estimator.params, estimator._refiner, estimator._search
    R0, t0 = entry.R[None].astype(float), entry.t[None].astype(float)
    truth = float(pose_scores(g, R0, t0, frame, p.pose)[0])
    refined = refined_truth(estimator, frame, entry)
    parts = pose_shares(g, refined.R, refined.t, frame, p.pose)[0]
    refined_ok = pose_errors(refined.R, refined.t, entry.R, entry.t, model, g).success_sym
    coarse = search.coarse(frame, p.search)
    near = near_templates(coarse, g, frame.camera, entry)
    order = np.argsort(-coarse.score)
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    best_rank = int(rank[near].min()) if near.any() else -1
    seeds = search.best(coarse, frame, p.search.seeds, p.search)
    seed_near = any(hypothesis_near(g, h, entry) for h in seeds)
    center = entry.R @ g.model_center + entry.t
    true_px = frame.camera.project(center)
    true_size = frame.camera.focal * g.model_diameter / np.linalg.norm(center)
    place_near = any(np.hypot(*(c - true_px)) < 0.25 * true_size and abs(np.log(size / true_size)) < np.log(1.5)
                     for c, size in search.places(coarse, p.search.windows))
    candidates = estimator.candidates(frame)
    near_c = [c for c in candidates if near_truth(c.R, c.t, entry, g)]
    turned = [c for c in candidates if turned_like_truth(c.R, c.t, entry, g)]
    near_climbed = refiner.best(near_c, frame, p.pose) if near_c else None
    near_right = near_climbed is not None and pose_errors(near_climbed.R, near_climbed.t, entry.R, entry.t,
                                                          model, g).success_sym
    final = chosen_pose(estimator, candidates, frame, p) if candidates else None
    if final is not None and p.pose.twin_check:
        final = check_twins(final, g, refiner, frame, p.pose).pose
    success = final is not None and pose_errors(final.R, final.t, entry.R, entry.t, model, g).success_sym
    found = final is not None and final.score >= p.pose.min_score
    if success and found:
        loss = "ok"
    elif refined.score < p.pose.min_score:
        loss = "wall"
    elif not near_c and turned:
        loss = "depth"
    elif not near_c:
        loss = "matching" if (seed_near or place_near) else "coarse"
    elif not near_right:
        loss = "drift"
    elif not success:
        loss = "choice"
    else:
        loss = "low"
    return dict(truth=truth, refined=refined.score, refined_ok=refined_ok, parts=parts, rank=best_rank,
                seed_near=seed_near, place_near=place_near, recall=bool(near_c),
                near_score=max((c.score for c in near_c), default=0.0),
                best_candidate=max((c.score for c in candidates), default=0.0),
                final=final.score if final is not None else 0.0, success=success, loss=loss,
                turned=min((depth_ratio(c, entry, g) for c in turned), key=lambda r: abs(np.log(r)), default=0.0),
                near_climbed=near_climbed.score if near_climbed is not None else 0.0, near_right=near_right,
                depth=depth_ratio(final, entry, g) if final is not None else 0.0,
                visible=getattr(entry, "visible_fraction", None))


def ceilings(d: dict, min_score: float) -> tuple[bool, bool]:
    """Would the image be right with a perfect search (the refined truth among the candidates,
    the score choosing: kept where it outscores the final pose), and with a perfect search and
    choice (kept wherever it is right and found)? What the score allows, whatever the search."""
    truth_right = d["refined_ok"] and d["refined"] >= min_score
    right = d["loss"] == "ok"
    return right or (truth_right and d["refined"] > d["final"]), right or truth_right


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=8, parts=TUNING, conditions=["occl30+clutter"], start=True)
    parser.add_argument("overrides", nargs="*", help="flat parameters, e.g. search.seeds=256")
    args = parser.parse_args(argv)
    params = overridden_params(args.overrides)
    cache = REPO / "data" / "bench"
    print("| part | condition | image | truth | refined (ok) | conf / expl / sig | coarse rank | seed / place near "
          "| recall (best near) | turned, depth x | near climbed | best cand. | final (success) | depth x "
          "| truth > final | loss |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    tally: dict[tuple[str, str], Counter] = {}
    for name, step in bench_steps(args.parts, cache).items():
        graph, model = graph_and_model(step, cache)
        estimator = Estimator(graph, params)
        for condition in args.conditions:
            for _, entry, _, frame in cached_frames(cache, name, condition, params, args.start, args.n):
                d = diagnose(estimator, frame, entry, model)
                counts = tally.setdefault((part_set(name), condition), Counter())
                counts[d["loss"]] += 1
                counts.update(k for k, held in zip(CEILINGS, ceilings(d, params.pose.min_score)) if held)
                s = d["parts"]
                print(f"| {name} | {condition} | {entry.image.split('/')[-1]} | {d['truth']:.2f} | "
                      f"{d['refined']:.2f} ({'y' if d['refined_ok'] else 'n'}) | "
                      f"{s.confirmed:.2f} / {s.explained:.2f} / {s.significance:.2f} | {d['rank']} | "
                      f"{'y' if d['seed_near'] else 'n'} / {'y' if d['place_near'] else 'n'} | "
                      f"{'y' if d['recall'] else 'n'} ({d['near_score']:.2f}) | {d['turned']:.2f} | "
                      f"{d['near_climbed']:.2f} ({'y' if d['near_right'] else 'n'}) | {d['best_candidate']:.2f} | "
                      f"{d['final']:.2f} ({'y' if d['success'] else 'n'}) | {d['depth']:.2f} | "
                      f"{'y' if d['refined'] > d['final'] else 'n'} | {d['loss']} |", flush=True)
        estimator.close()
    print("\n| set | condition | images | " + " | ".join(LOSSES + CEILINGS) + " |")
    print("|---|---|---|" + "---|" * len(LOSSES + CEILINGS))
    for (s, c), counts in sorted(tally.items()):
        print(f"| {s} | {c} | {sum(counts[k] for k in LOSSES)} | "
              + " | ".join(str(counts[k]) for k in LOSSES + CEILINGS) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Why a near-truth candidate loses: per image of the cached bench scenes, the estimator's
path replayed stage by stage, and the loss classed.

    python bench/choice_losses.py [--n 6] [--parts sharp_bracket ...] [--conditions clean ...] \
        [group.key=value ...]

A *near* candidate lies within 15 degrees and 10 % of the diameter of the truth
(bench/hypothesis_recall.py's ``near_truth``); *right* is CONVENTIONS.md's success up to
the part's exact symmetries, as *near* is (the flange turned by its bolt circle, the screw
by its half turn about its axis; how many ``ok`` are right only so is counted apart). The
estimator's path (``Estimator._candidates``, ``PoseRefiner.finalists``, ``check_rivals``,
``check_twins``) is replayed at the parameters given, and the loss is the first that applies:

- ``ok``: the final pose is right and found (its score at least ``pose.min_score``; the
  confidence floor ``pose.min_confidence`` is not applied); ``low``: right but not found;
- ``twin``: the pose before the twin check was right, the check turned it (d);
- ``wall``: the truth refined like a hypothesis and polished scores below ``pose.min_score``;
- ``stopped``: no near candidate, but one appears when every generator runs
  (``search.enough_score`` 1.01): a wrong pose stopped the generators early (c);
- ``none``: no near candidate at all (the search or the matching: bench/occlusion_diagnosis.py);
- ``drift``: the best near candidate, climbed and polished as the estimator would, is not
  right (a);
- ``dropped``: climbed and polished it is right and outscores the chosen pose, but it was not
  among the starts climbed (``pose.climb_candidates``, the dedupe) or the climb stopped at a
  ``CLEAR_SCORE`` pose first (c);
- ``outscored``: climbed and polished it is right, and a wrong pose scores no lower (b); the
  wrong pose's kind: ``twin`` (within the near bounds of the truth turned by one of the
  graph's near symmetries), ``smaller`` (its centre 1.15x as far from the camera or more,
  projected within the truth's outline: the part's own inner edges), ``elsewhere`` (its
  projected centre half the truth's projected diameter away or more: clutter), else
  ``look-alike`` (same place and size, other rotation).

Of the choice losses (``stopped``, ``drift``, ``dropped``, ``outscored``), those whose refined
truth scores higher than the chosen pose are counted apart: there the score would have
picked the truth, and the search, refinement or selection did not reach it.

Columns: the refined truth's score (not computed for ``ok``, ``low``, ``twin``), the score
of the best near candidate as handed to the climb, its rank among the candidates, whether
it was climbed, its score climbed and polished, the chosen pose's score (before the twin
check) and its errors against the truth (rotation, degrees; translation, diameters).
``--no-rivals`` replays the choice as it was before the rival check
(``symmetry.check_rivals``): the best climbed pose, polished.
"""
from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from bench.accuracy import (TUNING, add_scene_arguments, bench_steps, cached_frames, graph_and_model,  # noqa: E402
                            overridden_params, part_set)
from bench.hypothesis_recall import chosen_pose, near_truth  # noqa: E402
from bench.occlusion_diagnosis import refined_truth  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, pose_errors  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.refinement import distinct_poses  # noqa: E402
from brepose_ros.online.regions import region_groups  # noqa: E402
from brepose_ros.online.scoring import CLEAR_SCORE  # noqa: E402
from brepose_ros.online.symmetry import check_twins  # noqa: E402
from brepose_ros.online.workers import SERIAL  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402

LOSSES = ("ok", "low", "twin", "wall", "stopped", "none", "drift", "dropped", "outscored")
KINDS = ("twin", "smaller", "elsewhere", "look-alike")
#: the choice losses proper: a near candidate existed, or would have without the early stop
CHOICE = ("stopped", "drift", "dropped", "outscored")


def candidates_and_best(estimator: Estimator, frame: Frame, p: EstimatorParams, rivals: bool = True):
    """The candidates and the chosen pose before the twin check, as ``Estimator.estimate``
    gets them at parameters ``p``; without ``rivals`` the best climbed pose, polished, as
    before the rival check (main cb60954)."""
    candidates, best = estimator._candidates(estimator._image_work(p, SERIAL), frame, region_groups(frame, p.matching),
                                             {})
    if candidates and best is None:
        best = chosen_pose(estimator, candidates, frame, p, rivals)
    return candidates, best


def wrong_kind(pose, entry, graph, camera) -> str:
    """What kind of wrong pose outscores the truth (module doc)."""
    near = np.nonzero(~graph.exact_symmetries)[0]
    if len(near):
        R, t = graph.symmetric_poses(entry.R.astype(float), entry.t.astype(float), near)
        twins = [SimpleNamespace(R=R_k, t=t_k) for R_k, t_k in zip(R, t)]
        if any(near_truth(pose.R, pose.t, twin, graph) for twin in twins):
            return "twin"
    true_centre, centre = entry.R @ graph.model_center + entry.t, pose.R @ graph.model_center + pose.t
    true_size = camera.focal * graph.model_diameter / np.linalg.norm(true_centre)
    offset = np.hypot(*(camera.project(centre) - camera.project(true_centre)))
    if offset >= 0.5 * true_size:
        return "elsewhere"
    if np.linalg.norm(centre) >= 1.15 * np.linalg.norm(true_centre):
        return "smaller"
    return "look-alike"


def classify(estimator: Estimator, frame: Frame, entry, model: ModelPoints, rivals: bool = True) -> dict:
    g, p, refiner = estimator.graph, estimator.params, estimator._refiner
    candidates, chosen = candidates_and_best(estimator, frame, p, rivals)
    right = lambda c: c is not None and pose_errors(c.R, c.t, entry.R, entry.t, model, g).success_sym  # noqa: E731
    final = check_twins(chosen, g, refiner, frame, p.pose)[0] if chosen is not None and p.pose.twin_check else chosen
    row = dict(truth=np.nan, near=np.nan, rank=-1, climbed="-", near_final=np.nan,
               chosen=chosen.score if chosen else 0.0, rot=np.nan, centre=np.nan, kind="")
    if chosen is not None:
        e = pose_errors(chosen.R, chosen.t, entry.R, entry.t, model, g)
        row.update(rot=e.rotation_deg, centre=e.translation_mm / (g.model_diameter * 1000))
    if right(final):
        plain = pose_errors(final.R, final.t, entry.R, entry.t, model, g).success
        return row | dict(loss="ok" if final.score >= p.pose.min_score else "low", kind="" if plain else "sym")
    if right(chosen):
        return row | dict(loss="twin")
    row["truth"] = refined_truth(estimator, frame, entry).score
    if row["truth"] < p.pose.min_score:
        return row | dict(loss="wall")
    ordered = sorted(candidates, key=lambda c: -c.score)
    near = [k for k, c in enumerate(ordered) if near_truth(c.R, c.t, entry, g)]
    if not near:
        every = EstimatorParams().with_flat(p.flat() | {"search.enough_score": 1.01})
        full, _ = estimator._candidates(estimator._image_work(every, SERIAL), frame,
                                        region_groups(frame, every.matching), {})
        stopped = any(near_truth(c.R, c.t, entry, g) for c in full)
        return row | dict(loss="stopped" if stopped else "none")
    best_near = ordered[near[0]]
    starts = distinct_poses(ordered, p.pose.climb_candidates, g.model_diameter)
    climbed_starts = []
    for start in starts:  # the starts ``PoseRefiner.best`` climbs before a CLEAR_SCORE pose stops it
        climbed_starts.append(start)
        if refiner.climb(start, frame, p.pose).score >= CLEAR_SCORE:
            break
    was_climbed = any(near_truth(c.R, c.t, entry, g) for c in climbed_starts)
    finished = refiner.polish(refiner.climb(best_near, frame, p.pose), frame, p.pose)
    row.update(near=best_near.score, rank=near[0], climbed="y" if was_climbed else "n", near_final=finished.score)
    if not right(finished):
        return row | dict(loss="drift")
    if finished.score > chosen.score:
        return row | dict(loss="dropped")
    return row | dict(loss="outscored", kind=wrong_kind(chosen, entry, g, frame.camera))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=6, parts=TUNING, conditions=["clean", "clutter"], start=True)
    parser.add_argument("--no-rivals", action="store_true",
                        help="the final choice without the rival check (the best climbed pose, polished)")
    parser.add_argument("overrides", nargs="*", help="flat parameters, e.g. pose.climb_candidates=4")
    args = parser.parse_args(argv)
    params = overridden_params(args.overrides)
    cache = REPO / "data" / "bench"
    print("| part | condition | image | best near (rank, climbed) | near climbed+polished | chosen | "
          "chosen rot deg / centre d | loss | wrong kind |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    tally: dict[tuple[str, str], Counter] = {}
    kinds: dict[tuple[str, str], Counter] = {}
    for name, step in bench_steps(args.parts, cache).items():
        graph, model = graph_and_model(step, cache)
        estimator = Estimator(graph, params)
        for condition in args.conditions:
            for _, entry, _, frame in cached_frames(cache, name, condition, params, args.start, args.n):
                d = classify(estimator, frame, entry, model, rivals=not args.no_rivals)
                key = (part_set(name), condition)
                tally.setdefault(key, Counter())[d["loss"]] += 1
                if d["kind"]:
                    kinds.setdefault(key, Counter())[d["kind"]] += 1
                if d["loss"] in CHOICE and d["truth"] > d["chosen"]:
                    kinds.setdefault(key, Counter())["truth higher"] += 1
                print(f"| {name} | {condition} | {entry.image.split('/')[-1]} | {d['truth']:.3f} | "
                      f"{d['near']:.3f} ({d['rank']}, {d['climbed']}) | {d['near_final']:.3f} | {d['chosen']:.3f} | "
                      f"{d['rot']:.0f} / {d['centre']:.2f} | {d['loss']} | {d['kind']} |", flush=True)
        estimator.close()
    print("\n| set | condition | images | " + " | ".join(LOSSES) + " | outscored by " + " / ".join(KINDS)
          + " | ok only up to exact symmetry | choice losses whose refined truth outscores the chosen pose |")
    print("|---|---|---|" + "---|" * (len(LOSSES) + 3))
    for key, counts in sorted(tally.items()):
        print(f"| {key[0]} | {key[1]} | {sum(counts.values())} | " + " | ".join(str(counts[k]) for k in LOSSES)
              + " | " + " / ".join(str(kinds.get(key, Counter())[k]) for k in KINDS)
              + f" | {kinds.get(key, Counter())['sym']} | {kinds.get(key, Counter())['truth higher']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Why a reported pose near the truth misses the success bounds: the estimator's near misses
of a saved accuracy run, their errors split in the camera frame, and where the refinement
takes the truth itself.

    python bench/near_misses.py RESULTS.json [MORE.json ...] [--max-rotation 10] [--max-add-s 0.1]
                                [--polish-rounds 10] [--set group.key=value ...]

A near miss is an image of the runs (bench/accuracy.py's cached scenes, varied look, seed 100)
whose pose was reported found and is not right up to symmetry, within ``--max-rotation``
degrees and ADD-S ``--max-add-s`` diameters of the truth. Each is estimated again with
the runs' parameters (the defaults with the flat overrides given; the estimator repeats to
the bit) and its error split, against the
equivalent truth nearest it (``symmetric_truth``), into

- ``depth``: the part's centre moved along the truth's line of sight, in success bounds
  (5 % of the diameter; + is farther);
- ``lateral``: the centre moved across that line, in bounds;
- ``swing``: the part's own turn, degrees, about the line of sight (``roll``) and across it
  (``tilt``); ``lever``: the share of the translation error the turn alone makes, moving
  the model frame's origin about the part's centre (CONVENTIONS.md's translation is the
  origin's).

``px`` is the part's projected diameter; ``bound px`` the change of its projected size that a
depth error of one bound makes (0.05 px^2 / f). The truth is then taken through the
estimator's own refinement: ``polish`` (``PoseRefiner.polish``: pairings on edge pixels at
``pose.inlier_pixels``, guarded), ``fixed point`` (``--polish-rounds`` pairings, unguarded:
where the polish's cost settles), ``refined`` (as a hypothesis: line rounds, then polished;
``occlusion_diagnosis.refined_truth``) and ``climbed`` (refined, climbed over neighbouring
views, polished). Each reports score, depth, lateral and rotation, and y where right. The
fixed point run from the reported pose as well tells whether both settle in one place.

The verdict, the first that applies: ``polish`` (the polish takes the truth out of the
bounds: its cost is biased there), ``lines`` (the hypothesis refinement does), ``climb`` (the
refined truth is right, the climb walks off it to a higher score), ``score`` (the climbed
truth is right but scores below the reported pose: the score prefers the near miss),
``search`` (the climbed truth is right and scores at least the reported pose: the search
never offered it).
"""
from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from bench.accuracy import bench_steps, cached_frames, graph_and_model, overridden_params, scene_path  # noqa: E402
from bench.occlusion_diagnosis import refined_truth  # noqa: E402
from brepose_ros.evaluation.metrics import pose_errors, symmetric_truth  # noqa: E402
from brepose_ros.geometry import rotation_angle_deg  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.refinement import Candidate, align_on_edges  # noqa: E402
from brepose_ros.online.scoring import pose_scores  # noqa: E402

#: CONVENTIONS.md's translation bound, a share of the diameter
BOUND = 0.05


def near_misses(paths: list[Path], max_rotation: float, max_add_s: float) -> list[tuple[str, str, int]]:
    """(part, condition, image index) of the runs' found, wrong poses near the truth."""
    out = []
    for path in paths:
        for row in json.loads(path.read_text())["rows"]:
            for record in row["images"]:
                if (record["found"] and not record["success_sym"] and record["rotation_sym_deg"] < max_rotation
                        and record["add_s"] < max_add_s):
                    out.append((row["part"], row["condition"], int(Path(record["image"]).stem)))
    return sorted(out)


def split_error(R, t, R_true, t_true, graph, model) -> dict:
    """The pose's error against the truth in the camera frame (module doc); lengths in bounds
    (of the metric's diameter, ``ModelPoints.diameter``, as the success bound is)."""
    bound = BOUND * model.diameter
    c, c_true = R @ graph.model_center + t, R_true @ graph.model_center + t_true
    ray = c_true / np.linalg.norm(c_true)
    moved = c - c_true
    along = float(moved @ ray)
    w = cv2.Rodrigues(R @ R_true.T)[0].ravel()  # the turn's axis times its angle, camera frame
    roll = float(w @ ray)
    lever = (R - R_true) @ graph.model_center  # the origin's move from turning about the centre
    return {"depth": along / bound, "lateral": float(np.linalg.norm(moved - along * ray)) / bound,
            "rotation": rotation_angle_deg(R, R_true), "roll": float(np.degrees(roll)),
            "tilt": float(np.degrees(np.linalg.norm(w - roll * ray))),
            "translation": float(np.linalg.norm(t - t_true)) / bound,
            "lever": float(np.linalg.norm(lever)) / max(float(np.linalg.norm(t - t_true)), 1e-12)}


def verdict(right: dict, climbed_score: float, reported_score: float) -> str:
    """The near miss's cause (module doc) from which refinements of the truth stay right."""
    for stage in ("polish", "lines", "climb"):
        if not right[stage]:
            return stage
    return "score" if climbed_score < reported_score else "search"


def right_of(R, t, entry, graph, model) -> bool:
    return bool(pose_errors(R, t, entry.R, entry.t, model, graph).success_sym)


def described(name: str, R, t, score: float, entry, graph, model) -> str:
    """One pose's row cells: score, depth / lateral bounds, rotation, and y if right."""
    R_true, t_true = symmetric_truth(R, entry.R, entry.t, graph)
    e = split_error(R, t, R_true, t_true, graph, model)
    right = right_of(R, t, entry, graph, model)
    return f"{name} {score:.3f} d{e['depth']:+.2f} l{e['lateral']:.2f} r{e['rotation']:.1f}{' y' if right else ''}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", type=Path)
    parser.add_argument("--max-rotation", type=float, default=10.0, help="degrees")
    parser.add_argument("--max-add-s", type=float, default=0.1, help="diameters")
    parser.add_argument("--polish-rounds", type=int, default=10, help="pairings of the unguarded fixed point")
    parser.add_argument("--set", nargs="*", default=[], help="flat parameters, e.g. pose.polish_fine_pixels=0")
    args = parser.parse_args(argv)
    params = overridden_params(args.set)
    p = params.pose
    cache = REPO / "data" / "bench"
    misses = near_misses(args.results, args.max_rotation, args.max_add_s)
    print(f"{len(misses)} near misses\n")
    print("| part | condition | image | look | px | bound px | reported: depth / lateral / translation (bounds) "
          "| roll / tilt deg | lever | scores: reported / truth | polish | fixed point from truth | "
          "fixed point from reported | refined | climbed | verdict |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    verdicts = Counter()
    for name, step in bench_steps(sorted({m[0] for m in misses}), cache).items():
        graph, model = graph_and_model(step, cache)
        estimator = Estimator(graph, params)
        refiner = estimator._refiner
        for part, condition, i in misses:
            if part != name:
                continue
            _, entry, image, frame = next(cached_frames(cache, name, condition, params, i, 1))
            est = estimator.estimate(image, frame.camera)
            R_true, t_true = symmetric_truth(est.R, entry.R, entry.t, graph)
            e = split_error(est.R, est.t, R_true, t_true, graph, model)
            centre = R_true @ graph.model_center + t_true
            px = frame.camera.focal * model.diameter / np.linalg.norm(centre)
            look = json.loads((scene_path(cache, name, condition) / "gt.json").read_text())[i]["look"]
            look_text = f"blur {look['blur']:.2f}" + (f" motion {look['motion']:.0f}" if look["motion"] else "") \
                + f" {look['background']}"
            R0, t0 = entry.R[None].astype(float), entry.t[None].astype(float)
            truth_score = float(pose_scores(graph, R0, t0, frame, p)[0])
            polished = refiner.polish(Candidate(truth_score, R0[0], t0[0], None), frame, p)
            fixed = []
            for R_s, t_s in ((R0, t0), (est.R[None], est.t[None])):
                R_f, t_f = align_on_edges(R_s, t_s, graph, frame, radii=np.full((1, args.polish_rounds),
                                                                              p.inlier_pixels))
                fixed.append((R_f[0], t_f[0], float(pose_scores(graph, R_f, t_f, frame, p)[0])))
            refined = refined_truth(estimator, frame, entry)
            climbed = refiner.polish(refiner.climb(refined, frame, p), frame, p)
            cells = [described("", c.R, c.t, c.score, entry, graph, model) for c in (polished,)]
            cells += [described("", R_f, t_f, s, entry, graph, model) for R_f, t_f, s in fixed]
            cells += [described("", c.R, c.t, c.score, entry, graph, model) for c in (refined, climbed)]
            cause = verdict({"polish": right_of(polished.R, polished.t, entry, graph, model),
                             "lines": right_of(refined.R, refined.t, entry, graph, model),
                             "climb": right_of(climbed.R, climbed.t, entry, graph, model)}, climbed.score, est.score)
            verdicts[cause] += 1
            print(f"| {name} | {condition} | {i} | {look_text} | {px:.0f} | {BOUND * px * px / frame.camera.focal:.1f} "
                  f"| {e['depth']:+.2f} / {e['lateral']:.2f} / {e['translation']:.2f} | {e['roll']:+.1f} / "
                  f"{e['tilt']:.1f} | {e['lever']:.2f} | {est.score:.3f} / {truth_score:.3f} | "
                  + " | ".join(cells) + f" | {cause} |", flush=True)
        estimator.close()
    print("\n" + ", ".join(f"{cause} {count}" for cause, count in verdicts.most_common()))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""What the wrong reported poses are, and whether a generic flip check would right them.

    python bench/flips.py [--n 8] [--start 0] [--parts sharp_bracket ...] [--conditions clean clutter] [--label NAME]

For each part, condition and image of bench/accuracy.py's cached scenes (varied look, seed
100, 5-degree graphs), the estimator with default parameters. Every reported pose (score >=
``pose.min_score``) that fails success (up to the part's exact symmetries) is described by
the turn that relates it to the truth: its angle, its axis against the model's principal
axes (of the graph's edges, about ``model_center``) and, in the camera, against the line of
sight; how far the part's centre moved along the line of sight (``depth``: the estimate's
distance over the truth's) and across it (share of the diameter); and the truth's own score,
refined as a hypothesis is (``refined_scores``) and polished: whether the score prefers the
wrong pose.

The generic alternates of every reported pose, the candidates of a flip check that needs no
compiled symmetry: the half turn about each principal axis through the centre, and each of
those followed by a half turn about the line of sight (the *tilt mirror*: for a part with a
mirror plane it projects like the pose, only seen from the other side). Each is refined like
a climb step (``CLIMB_ROUNDS``), the best climbed and polished, and kept if the twin check's
rule prefers it (``symmetry.pick_by_evidence``). Per row: reported, right and wrong poses; of
the wrong ones, the half turns (more than 150 degrees, centre depth within 10 %) and those at
another depth (more than 10 % off); wrong poses with an alternate starting within 15 degrees
of the truth; the check's rights made and broken, and its median time. Per-image records go to
data/bench/results/flips_LABEL.json.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import (PARTS, add_scene_arguments, bench_steps, distractor_meshes, graph_and_model,  # noqa: E402
                            scene)
from bench.occlusion_diagnosis import refined_truth  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.metrics import pose_errors  # noqa: E402
from brepose_ros.geometry import rotation_about, rotation_angle_deg  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.online.frame import Frame  # noqa: E402
from brepose_ros.online.refinement import CLIMB_ROUNDS, Candidate  # noqa: E402
from brepose_ros.online.symmetry import pick_by_evidence  # noqa: E402
from brepose_ros.online.workers import SERIAL  # noqa: E402

#: a wrong pose is a half turn beyond this angle, degrees, with its centre's depth within DEPTH_SAME
HALF_TURN_DEG = 150.0
DEPTH_SAME = 0.1
#: an alternate starting this near the truth, degrees, is within reach of the refinement and climb
REACH_DEG = 15.0


def principal_axes(graph: AspectGraph) -> np.ndarray:
    """(3, 3) rows: the principal axes of the graph's edges about ``model_center``, least spread first
    (edges weighted by their length, each as often as views draw it)."""
    seg = graph.seg_3d
    offset = seg.mean(axis=1) - graph.model_center
    weight = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    return np.linalg.eigh((offset * weight[:, None]).T @ offset)[1].T


def alternates(R: np.ndarray, t: np.ndarray, graph: AspectGraph, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(6, 3, 3), (6, 3): the pose's half turn about each principal axis through the centre, then
    each followed by a half turn about the line of sight (the tilt mirror); the centre stays put."""
    centre = R @ graph.model_center + t
    mirror = rotation_about(centre / np.linalg.norm(centre), np.pi)
    R_alt = np.array([M @ R @ rotation_about(axis, np.pi) for axis in axes for M in (np.eye(3), mirror)])
    return R_alt, centre - R_alt @ graph.model_center


def axis_angle(R: np.ndarray) -> tuple[np.ndarray, float]:
    """The unit axis and angle (degrees) of rotation R."""
    angle = rotation_angle_deg(np.eye(3), R)
    if angle > 179.0:  # the skew part vanishes near a half turn: the axis is the dominant column of R + I
        B = R + np.eye(3)
        axis = B[:, np.argmax(np.diag(B))]
    else:
        axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return axis / np.linalg.norm(axis), angle


def describe_wrong(est, entry, graph: AspectGraph, axes: np.ndarray) -> dict:
    """The turn from the truth to the wrong pose ``est`` (module doc)."""
    axis_model, angle = axis_angle(entry.R.T @ est.R)
    axis_cam, _ = axis_angle(est.R @ entry.R.T)
    true_centre, centre = entry.R @ graph.model_center + entry.t, est.R @ graph.model_center + est.t
    sight = true_centre / np.linalg.norm(true_centre)
    offset = centre - true_centre
    return {"angle": angle,
            "axis_to_principal_deg": np.degrees(np.arccos(np.clip(np.abs(axes @ axis_model), 0, 1))).tolist(),
            "axis_to_sight_deg": float(np.degrees(np.arccos(min(1.0, abs(axis_cam @ sight))))),
            "depth": float(np.linalg.norm(centre) / np.linalg.norm(true_centre)),
            "across": float(np.linalg.norm(offset - (offset @ sight) * sight) / graph.model_diameter)}


def flip_check(estimator: Estimator, frame: Frame, best: Candidate, axes: np.ndarray) -> tuple[Candidate, list]:
    """The generic alternates of ``best`` refined, the best climbed and polished, and the pose the twin
    check's rule keeps; and the alternates' start poses."""
    g, refiner, p = estimator.graph, estimator._refiner, estimator.params.pose
    R, t = alternates(best.R, best.t, g, axes)
    R_r, t_r, scores = refiner.refined_scores(R, t, frame, p, CLIMB_ROUNDS, SERIAL)
    k = int(np.argmax(scores))
    rival = refiner.polish(refiner.climb(Candidate(float(scores[k]), R_r[k], t_r[k], best.hypothesis), frame, p),
                           frame, p)
    return pick_by_evidence(best, [rival], g, frame, p)[0], list(R)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=8, parts=list(PARTS), conditions=["clean", "clutter"], start=True)
    parser.add_argument("--label", default="default")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    distractors = distractor_meshes(cache)
    records, rows = [], []
    for name, step in bench_steps(args.parts, cache).items():
        graph, model = graph_and_model(step, cache)
        estimator = Estimator(graph)
        p = estimator.params
        axes = principal_axes(graph)
        for condition in args.conditions:
            row = {"part": name, "condition": condition, "reported": 0, "right": 0, "wrong": 0, "half_turn": 0,
                   "other_depth": 0, "reachable": 0, "made": 0, "broken": 0, "ms": []}
            images = scene(cache, name, step, condition, range(args.start, args.start + args.n), distractors)
            for i, entry in enumerate(images.entries, start=args.start):
                image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
                est = estimator.estimate(image, images.camera)
                if not est.found:
                    continue
                _, frame = Frame.detect(image, images.camera, p.edges, SERIAL)
                right = pose_errors(est.R, est.t, entry.R, entry.t, model, graph).success_sym
                clock = time.perf_counter()
                kept, starts = flip_check(estimator, frame, Candidate(est.score, est.R, est.t, None), axes)
                row["ms"].append(1000.0 * (time.perf_counter() - clock))
                kept_right = pose_errors(kept.R, kept.t, entry.R, entry.t, model, graph).success_sym
                record = {"part": name, "condition": condition, "image": i, "score": est.score, "right": right,
                          "check_score": kept.score, "check_right": kept_right,
                          "nearest_alternate_deg": min(rotation_angle_deg(R, entry.R) for R in starts)}
                row["reported"] += 1
                row["right"] += right
                row["made"] += kept_right and not right
                row["broken"] += right and not kept_right
                if not right:
                    record |= describe_wrong(est, entry, graph, axes)
                    record["truth_score"] = refined_truth(estimator, frame, entry).score
                    row["wrong"] += 1
                    row["half_turn"] += record["angle"] > HALF_TURN_DEG and abs(record["depth"] - 1) < DEPTH_SAME
                    row["other_depth"] += abs(record["depth"] - 1) >= DEPTH_SAME
                    row["reachable"] += record["nearest_alternate_deg"] < REACH_DEG
                    print(f"{name} {condition} {i}: score {est.score:.2f} truth {record['truth_score']:.2f}, "
                          f"{record['angle']:.0f} deg about an axis "
                          f"{np.round(record['axis_to_principal_deg']).astype(int)} deg from the principal axes, "
                          f"{record['axis_to_sight_deg']:.0f} from the line of sight; "
                          f"depth x{record['depth']:.2f}, across {record['across']:.2f} d; nearest alternate "
                          f"{record['nearest_alternate_deg']:.0f} deg; check {'right' if kept_right else 'wrong'}",
                          flush=True)
                records.append(record)
            rows.append(row)
        estimator.close()
    print("\n| part | condition | reported | right | wrong | half turns | other depth | alternate within "
          f"{REACH_DEG:g} deg | check: made / broken | check ms (median) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ms = f"{np.median(r['ms']):.0f}" if r["ms"] else "-"
        print(f"| {r['part']} | {r['condition']} | {r['reported']} | {r['right']} | {r['wrong']} | {r['half_turn']} | "
              f"{r['other_depth']} | {r['reachable']} | {r['made']} / {r['broken']} | {ms} |")
    out = cache / "results" / f"flips_{args.label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"rows": rows, "images": records}, indent=1, default=float) + "\n")
    print(f"\nwrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""How many wrong poses are twins of the truth, and what the twin check saw there.

    python bench/twins.py [--n 12] [--parts notched_plate flange shaft ...] [--conditions clean clutter]
                          [--label NAME] [--twin-check on|off]

For each part (default: the bench parts whose graphs hold near symmetries) and condition,
the estimator with default parameters on bench/accuracy.py's cached scenes. Every reported
pose (score >= ``pose.min_score``) that fails CONVENTIONS.md's success (up to the part's
exact symmetries, which make poses equivalent) is a *twin* when one
of the part's near symmetries applied to the truth (a stored turn, or any turn about a near
continuous axis) lies within the success bounds of it (rotation < 5 degrees, translation
< 5 % of the diameter): the image nearly shows the truth there. Per row: reported poses,
right ones, wrong ones, wrong ones that are twins, and the twin check's margin and ambiguity
on the right and the wrong poses. Per-image records go to
data/bench/results/twins_LABEL.json.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import CONDITIONS, PARTS, SCENES_VERSION, SPAN, distractor_meshes, scene, step_file  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, evaluate_scene, translation_error_mm  # noqa: E402
from brepose_ros.geometry import quaternion_from_matrix, rotation_about, rotation_angle_deg  # noqa: E402
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.synthetic.scenes import SceneConfig  # noqa: E402

SYMMETRIC_PARTS = ("notched_plate", "flange", "shaft", "mounting_plate", "motor1_holder")


def twin_of_truth(R_est, t_est, R_gt, t_gt, graph: AspectGraph) -> str | None:
    """Which near symmetry of the part, applied to the truth, lies within the success
    bounds of the estimate ('turn 180' for a stored turn by 180 degrees, 'axis 60' for a
    turn by 60 degrees about a near continuous axis), or None."""
    bound_mm = 0.05 * graph.model_diameter * 1000.0

    def within(R, t):
        return rotation_angle_deg(R_est, R) < 5.0 and translation_error_mm(t_est, t) < bound_mm

    near = ~graph.exact_symmetries
    for k, R, t in zip(np.nonzero(near)[0], *graph.symmetric_poses(R_gt, t_gt, near)):
        if within(R, t):
            return f"turn {rotation_angle_deg(np.eye(3), graph.symmetry_rotations[k]):.0f}"
    for point, axis in graph.symmetry_axes[~graph.exact_axes]:
        # the turn about the axis that brings the truth nearest the estimate (swing-twist)
        x, y, z, w = quaternion_from_matrix(R_gt.T @ R_est)
        angle = 2.0 * np.arctan2(np.array([x, y, z]) @ axis, w)
        turn = rotation_about(axis, angle)
        if abs(np.degrees(angle)) > 5.0 and within(R_gt @ turn, t_gt + R_gt @ (point - turn @ point)):
            return f"axis {abs(np.degrees((angle + np.pi) % (2 * np.pi) - np.pi)):.0f}"
    return None


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=12)
    parser.add_argument("--parts", nargs="*", default=list(SYMMETRIC_PARTS), choices=list(PARTS))
    parser.add_argument("--conditions", nargs="*", default=["clean", "clutter"], choices=list(CONDITIONS))
    parser.add_argument("--step-deg", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--twin-check", choices=("on", "off"), default="on")
    parser.add_argument("--label", default="default")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    base = EstimatorParams()
    params = dataclasses.replace(base, pose=dataclasses.replace(base.pose, twin_check=args.twin_check == "on"))
    distractors = distractor_meshes(cache)
    records, rows = [], []
    for name in args.parts:
        step = step_file(PARTS[name], cache)
        graph = AspectGraph.load(cached_graph_path(step, cache, args.step_deg))
        mesh = tessellate(load_step(step))
        model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        estimator = Estimator(graph, params)
        for condition in args.conditions:
            config = SceneConfig(span=SPAN, look="varied", **CONDITIONS[condition])
            folder = cache / f"scenes_v{SCENES_VERSION}_varied" / f"{name}_{condition}_{args.seed}"
            loaded = scene(step, folder, args.n, args.seed, config, distractors)
            row = dict(part=name, condition=condition, images=len(loaded.entries), found=0, right=0, wrong=0,
                       twins=0, kinds=[], margins_right=[], margins_wrong=[], ambiguous_right=0,
                       ambiguous_wrong=0, ms=[])
            for entry, result in zip(loaded.entries, evaluate_scene(loaded, estimator, model)):
                estimate, errors = result.estimate, result.errors
                row["ms"].append(1000 * estimate.timings.get("symmetry", 0.0))
                record = dict(part=name, condition=condition, image=result.image, found=estimate.found,
                              score=float(estimate.score), margin=estimate.symmetry_margin,
                              ambiguous=bool(estimate.ambiguous))
                if errors is not None:
                    right = errors.success_sym  # a pose turned by an exact symmetry is the same pose
                    twin = None if right else twin_of_truth(estimate.R, estimate.t, entry.R, entry.t, graph)
                    record.update(rotation_deg=errors.rotation_deg, right=right, twin=twin,
                                  R=estimate.R.ravel().tolist(), t=estimate.t.tolist())
                    row["found"] += 1
                    row["right" if right else "wrong"] += 1
                    row["margins_right" if right else "margins_wrong"].append(estimate.symmetry_margin)
                    row["ambiguous_right" if right else "ambiguous_wrong"] += estimate.ambiguous
                    if twin:
                        row["twins"] += 1
                        row["kinds"].append(twin)
                records.append(record)
                print(f"  {name} {condition} {result.image}: {json.dumps(record)}", file=sys.stderr)
            rows.append(row)
            out = cache / "results" / f"twins_{args.label}.json"
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(records, indent=1) + "\n")
        estimator.close()
    print(f"\ntwin check {args.twin_check}, {args.n} images per row, graphs at {args.step_deg:g} deg\n")
    print("| part | condition | reported | right | wrong | of them twins (which) | ambiguous right / wrong | "
          "twin check ms (median) |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        kinds = ", ".join(r["kinds"])
        print(f"| {r['part']} | {r['condition']} | {r['found']} | {r['right']} | {r['wrong']} | "
              f"{r['twins']}{f' ({kinds})' if kinds else ''} | {r['ambiguous_right']} / {r['ambiguous_wrong']} | "
              f"{np.median(r['ms']):.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""How many wrong poses are twins of the truth, with the twin check on, off or both.

    python bench/twins.py [--n 12] [--parts notched_plate flange shaft ...] [--conditions clean clutter]
                          [--label NAME] [--twin-check on|off ...] [--look varied|plain] [--span LOW HIGH]

For each part (default: the bench parts whose graphs hold near symmetries), condition and
``--twin-check`` setting (``--twin-check off on`` compares the two; each setting estimates
the scene in turn, and only the check's own time is printed, zero when it is off), the
estimator with default parameters on bench/accuracy.py's cached scenes (of ``--look`` and
``--span``; ``--look plain --span 0.25 0.6`` is ``SceneConfig()``'s). Every reported
pose (score >= ``pose.min_score``) that fails CONVENTIONS.md's success (up to the part's
exact symmetries, which make poses equivalent) is a *twin* when one
of the part's near symmetries applied to the truth (a stored turn, or any turn about a near
continuous axis) lies within the success bounds of it (rotation < 5 degrees, translation
< 5 % of the diameter): the image nearly shows the truth there. Per row: reported poses,
right ones, wrong ones, wrong ones that are twins, and the twin check's ambiguity on the right
and the wrong poses; a column names the part's symmetries as compiled (exact / near counts,
and the near turns' shares). Per-image records go to data/bench/results/twins_LABEL.json.
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

from bench.accuracy import (SPAN, add_scene_arguments, bench_steps, distractor_meshes, graph_and_model,  # noqa: E402
                            scene)
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, evaluate_scene, translation_error_mm  # noqa: E402
from brepose_ros.geometry import quaternion_from_matrix, rotation_about, rotation_angle_deg  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.synthetic.scenes import LOOKS  # noqa: E402

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


def describe(graph: AspectGraph) -> str:
    """The graph's symmetries: 'exact / near' counts (continuous axes among the exact ones),
    then the near turns' shares."""
    exact = int(graph.exact_symmetries.sum()) + int(graph.exact_axes.sum())
    near = ", ".join(f"{s:.2f}" for s in graph.symmetry_shares[~graph.exact_symmetries])
    return f"{exact} / {int((~graph.exact_symmetries).sum())}" + (f": {near}" if near else "")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_arguments(parser, n=12, parts=list(SYMMETRIC_PARTS), conditions=["clean", "clutter"])
    parser.add_argument("--step-deg", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--twin-check", nargs="+", choices=("on", "off"), default=["on"])
    parser.add_argument("--look", default="varied", choices=LOOKS)
    parser.add_argument("--span", type=float, nargs=2, default=SPAN, metavar=("LOW", "HIGH"))
    parser.add_argument("--label", default="default")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    base = EstimatorParams()
    settings = {check: dataclasses.replace(base, pose=dataclasses.replace(base.pose, twin_check=check == "on"))
                for check in args.twin_check}
    distractors = distractor_meshes(cache)
    out = cache / "results" / f"twins_{args.label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    records, rows = [], []
    for name, step in bench_steps(args.parts, cache).items():
        graph, model = graph_and_model(step, cache, args.step_deg)
        estimators = {check: Estimator(graph, params) for check, params in settings.items()}
        for condition in args.conditions:
            loaded = scene(cache, name, step, condition, args.n, distractors, args.look, tuple(args.span), args.seed)
            for check, estimator in estimators.items():
                rows.append(count_twins(loaded, estimator, model, name, condition, check, records))
            out.write_text(json.dumps(records, indent=1) + "\n")
        for estimator in estimators.values():
            estimator.close()
    print(f"\n{args.n} images per row, {args.look} look, span {args.span[0]:g}-{args.span[1]:g}, "
          f"graphs at {args.step_deg:g} deg\n")
    print("| part | symmetries (exact / near: shares) | condition | twin check | reported | right | wrong | "
          "of them twins (which) | ambiguous right / wrong | twin check ms (median) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        kinds = ", ".join(r["kinds"])
        print(f"| {r['part']} | {r['symmetries']} | {r['condition']} | {r['twin_check']} | {r['found']} | "
              f"{r['right']} | {r['wrong']} | {r['twins']}{f' ({kinds})' if kinds else ''} | "
              f"{r['ambiguous_right']} / {r['ambiguous_wrong']} | {np.median(r['ms']):.0f} |")
    return 0


def count_twins(loaded, estimator: Estimator, model: ModelPoints, name: str, condition: str, check: str,
                records: list) -> dict:
    """One table row: the poses of scene ``loaded`` sorted into right, wrong and twins of the
    truth; each image's record is appended to ``records``."""
    graph = estimator.graph
    row = dict(part=name, symmetries=describe(graph), condition=condition, twin_check=check, found=0, right=0,
               wrong=0, twins=0, kinds=[], ambiguous_right=0, ambiguous_wrong=0, ms=[])
    for entry, result in zip(loaded.entries, evaluate_scene(loaded, estimator, model)):
        estimate, errors = result.estimate, result.errors
        row["ms"].append(1000 * estimate.timings.get("symmetry", 0.0))
        record = dict(part=name, condition=condition, twin_check=check, image=result.image, found=estimate.found,
                      score=float(estimate.score), margin=estimate.symmetry_margin,
                      ambiguous=bool(estimate.ambiguous))
        if errors is not None:
            right = errors.success_sym  # a pose turned by an exact symmetry is the same pose
            twin = None if right else twin_of_truth(estimate.R, estimate.t, entry.R, entry.t, graph)
            record.update(rotation_deg=errors.rotation_deg, right=right, twin=twin,
                          R=estimate.R.ravel().tolist(), t=estimate.t.tolist())
            row["found"] += 1
            row["right" if right else "wrong"] += 1
            row["ambiguous_right" if right else "ambiguous_wrong"] += estimate.ambiguous
            if twin:
                row["twins"] += 1
                row["kinds"].append(twin)
        records.append(record)
        print(f"  {name} {condition} twin check {check} {result.image}: {json.dumps(record)}", file=sys.stderr)
    return row


if __name__ == "__main__":
    sys.exit(main())

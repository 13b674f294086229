"""Flips of near-symmetric parts with the twin check off and on, as a table.

    python bench/symmetry.py [--n 24] [--step-deg 5] [--parts notched_plate PATH.step ...]

For each part: its symmetries as compiled into the aspect graph, then ``--n`` clean images
(``SceneConfig()``, seed ``--seed``) estimated twice, with ``pose.twin_check`` off and on,
alternating image by image. A *flip* is a pose within ``FLIP_DEG`` of one of the truth's
twins under the part's near symmetries (the pose the image nearly shares with the truth).
Graphs and scenes are cached under data/bench/ (git-ignored).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, pose_errors  # noqa: E402
from brepose_ros.geometry import rotation_angle_deg  # noqa: E402
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402
from brepose_ros.synthetic import shapes  # noqa: E402
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene  # noqa: E402

FLIP_DEG = 10.0
DEFAULT_PARTS = ["notched_plate", str(REPO.parent / "shared" / "data" / "step" / "11_soarm100__Motor1_holder.step"),
                 str(REPO.parent / "shared" / "data" / "step" / "06_occt__screw.step")]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=24)
    parser.add_argument("--step-deg", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--parts", nargs="*", default=DEFAULT_PARTS)
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.parts:
        step = shapes.export_step(name, cache / f"{name}.step") if name in shapes.BUILTIN else Path(name)
        graph = AspectGraph.load(cached_graph_path(step, cache, args.step_deg))
        print(f"{step.stem}: {describe(graph)}", file=sys.stderr)
        folder = cache / f"scene_{step.stem}_clean_{args.n}_{args.seed}"
        if not (folder / "gt.json").exists():
            generate_scene(step, folder, args.n, seed=args.seed, config=SceneConfig())
        mesh = tessellate(load_step(step))
        model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        base = EstimatorParams()
        settings = {on: dataclasses.replace(base, pose=dataclasses.replace(base.pose, twin_check=on))
                    for on in (False, True)}
        estimators = {on: Estimator(graph, params) for on, params in settings.items()}
        tally = {on: dict(flips=0, success=0, success_sym=0, ambiguous=0, ambiguous_flips=0, ms=[]) for on in settings}
        scene = load_scene(folder)
        for i, entry in enumerate(scene.entries):
            image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
            for on in ((False, True) if i % 2 == 0 else (True, False)):
                estimate = estimators[on].estimate(image, scene.camera)
                row = tally[on]
                row["ms"].append(1000 * estimate.timings.get("symmetry", 0.0))
                if not estimate.found:
                    continue
                errors = pose_errors(estimate.R, estimate.t, entry.R, entry.t, model, graph)
                flip = is_flip(graph, estimate.R, entry.R, entry.t)
                row["flips"] += flip
                row["success"] += errors.success
                row["success_sym"] += errors.success_sym
                row["ambiguous"] += estimate.ambiguous
                row["ambiguous_flips"] += estimate.ambiguous and flip
                if on:
                    print(f"  {entry.image}: rot {errors.rotation_deg:6.1f} deg, score {estimate.score:.2f}, "
                          f"margin {estimate.symmetry_margin}, flip {flip}", file=sys.stderr)
        for estimator in estimators.values():
            estimator.close()
        rows.append((step.stem[:32], describe(graph), len(scene.entries), tally))
    print("\n| part | symmetries (exact / near: shares) | images | flips off / on | success off / on | "
          "success up to exact symmetry on | ambiguous on (of them flips) | twin check ms (median) |")
    print("|---|---|---|---|---|---|---|---|")
    for part, symmetries, n, t in rows:
        off, on = t[False], t[True]
        print(f"| {part} | {symmetries} | {n} | {off['flips']} / {on['flips']} | {off['success']} / {on['success']} | "
              f"{on['success_sym']} | {on['ambiguous']} ({on['ambiguous_flips']}) | {np.median(on['ms']):.0f} |")
    return 0


def describe(graph: AspectGraph) -> str:
    exact = int(graph.exact_symmetries.sum()) + int(graph.exact_axes.sum())
    near = ", ".join(f"{s:.2f}" for s in graph.symmetry_shares[~graph.exact_symmetries])
    return f"{exact} / {int((~graph.exact_symmetries).sum())}" + (f": {near}" if near else "")


def is_flip(graph: AspectGraph, R_est, R_gt, t_gt) -> bool:
    """Whether the pose lies within FLIP_DEG of a twin of the truth under a near symmetry."""
    near = ~graph.exact_symmetries
    if not near.any():
        return False
    twins, _ = graph.symmetric_poses(R_gt, t_gt, near)
    return any(rotation_angle_deg(R_est, R) < FLIP_DEG for R in twins)


if __name__ == "__main__":
    sys.exit(main())

"""Success and time of the hypothesis generators (``search.generators``: the paper's
region-normalised tetrads, the template search, both) on the scenes of bench/accuracy.py.

    python bench/generators.py [--n 12] [--parts ...] [--conditions ...] [--generators tetrad search both]

Scenes and aspect graphs are those of bench/accuracy.py (cached under data/bench/).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import CONDITIONS, REAL_PARTS, part_step  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, evaluate_scene, scene_summary  # noqa: E402
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import GENERATORS, EstimatorParams  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402
from brepose_ros.synthetic.scenes import generate_scene  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=12, help="images per part and condition")
    parser.add_argument("--step-deg", type=float, default=5.0, help="aspect graph view spacing")
    parser.add_argument("--parts", nargs="*", help="built-in names or STEP files")
    parser.add_argument("--conditions", nargs="*", default=["clean", "clutter", "occl30+clutter", "occl50"],
                        choices=list(CONDITIONS))
    parser.add_argument("--generators", nargs="*", default=list(GENERATORS), choices=list(GENERATORS))
    parser.add_argument("--seed", type=int, default=100)
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    cache.mkdir(parents=True, exist_ok=True)
    parts = args.parts or ["sharp_bracket", "rounded_bracket"] + [
        str(REPO.parent / "shared" / "data" / "step" / p) for p in REAL_PARTS]
    print("| part | condition | generators | success | ADD-S < 0.1 | median rot (deg) | median ms |")
    print("|---|---|---|---|---|---|---|", flush=True)
    for name in parts:
        step = part_step(name, cache)
        graph = AspectGraph.load(cached_graph_path(step, cache, args.step_deg))
        mesh = tessellate(load_step(step))
        model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        estimator = Estimator(graph)
        for condition in args.conditions:
            folder = cache / f"scene_{step.stem}_{condition}_{args.n}_{args.seed}"
            if not (folder / "gt.json").exists():
                generate_scene(step, folder, args.n, seed=args.seed, config=CONDITIONS[condition])
            scene = load_scene(folder)
            for generators in args.generators:
                estimator.params = EstimatorParams().with_flat({"search.generators": generators})
                s = scene_summary(evaluate_scene(scene, estimator, model))
                print(f"| {step.stem[:32]} | {condition} | {generators} | {s['success']:.2f} | "
                      f"{s['add_s_below_0.1']:.2f} | {s['median_rotation_deg']:.2f} | {s['median_time_ms']:.0f} |",
                      flush=True)
        estimator.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())

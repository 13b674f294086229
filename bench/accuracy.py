"""Accuracy of the estimator on generated scenes, as a table for the README.

    python bench/accuracy.py [--n 12] [--step-deg 5] [--parts sharp_bracket rounded_bracket ...]

Parts are built-in names or STEP paths; by default the paper's two brackets plus two real
parts from ../shared/data/step when that folder is beside the clone. Each part is seen in
five conditions: clean and centred; off-centre among 3 clutter shapes; 30 % occluded;
off-centre with 30 % occlusion and 3 clutter shapes; 50 % occlusion. Aspect graphs and scenes are cached under data/bench/ (git-ignored).
Metrics follow ../shared/CONVENTIONS.md.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.synthetic import shapes  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, evaluate_scene, scene_summary  # noqa: E402
from brepose_ros.synthetic.scenes import SceneConfig, generate_scene  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402

CONDITIONS = {
    "clean": SceneConfig(),
    "clutter": SceneConfig(offcenter=True, clutter=3),
    "occl30": SceneConfig(occlusion=0.3),
    "occl30+clutter": SceneConfig(offcenter=True, occlusion=0.3, clutter=3),
    "occl50": SceneConfig(occlusion=0.5),
}
REAL_PARTS = ["09_soarm100__Base_attachment.step", "11_soarm100__Motor1_holder.step"]


def part_step(name: str, cache: Path) -> Path:
    if name in shapes.BUILTIN:
        return shapes.export_step(name, cache / f"{name}.step")
    return Path(name)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=12, help="images per part and condition")
    parser.add_argument("--step-deg", type=float, default=5.0, help="aspect graph view spacing")
    parser.add_argument("--parts", nargs="*", help="built-in names or STEP files")
    parser.add_argument("--conditions", nargs="*", default=list(CONDITIONS), choices=list(CONDITIONS))
    parser.add_argument("--seed", type=int, default=100)
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    cache.mkdir(parents=True, exist_ok=True)
    parts = args.parts
    if not parts:
        parts = ["sharp_bracket", "rounded_bracket"]
        real = REPO.parent / "shared" / "data" / "step"
        parts += [str(real / p) for p in REAL_PARTS if (real / p).exists()]
    rows = []
    for name in parts:
        step = part_step(name, cache)
        graph = AspectGraph.load(cached_graph_path(step, cache, args.step_deg))
        estimator = Estimator(graph)
        mesh = tessellate(load_step(step))
        model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        for condition in args.conditions:
            folder = cache / f"scene_{step.stem}_{condition}_{args.n}_{args.seed}"
            if not (folder / "gt.json").exists():
                generate_scene(step, folder, args.n, seed=args.seed, config=CONDITIONS[condition])
            summary = scene_summary(evaluate_scene(load_scene(folder), estimator, model))
            rows.append((step.stem[:32], condition, graph.n_views, summary))
            print(f"{step.stem[:32]:32s} {condition:15s} success {summary['success']:.2f}", file=sys.stderr)
        estimator.close()
    print("\n| part | condition | views | success | er < 0.01 | view in 3 nearest (final / matched) | "
          "ADD-S < 0.1 | median rot (deg) | median trans (mm) | median ms |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for part, condition, views, s in rows:
        print(f"| {part} | {condition} | {views} | {s['success']:.2f} | {s['er_below_0.01']:.2f} | "
              f"{s['view_among_3_nearest']:.2f} / {s['matched_view_among_3_nearest']:.2f} | "
              f"{s['add_s_below_0.1']:.2f} | {s['median_rotation_deg']:.2f} | "
              f"{s['median_translation_mm']:.2f} | {s['median_time_ms']:.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Can the score be thresholded? Precision and recall of `found` against the score.

    python bench/confidence.py [--n 12] [--part sharp_bracket] [--others cube cylinder sample_bracket]

Positives: images of the part (clean, and off-centre with 30 % occlusion and clutter); a
detection is correct when the pose succeeds (rotation < 5 deg, translation < 5 % of the
diameter). Negatives: images of *other* parts and of the part's clutter only, where any
detection is wrong. For each threshold on the score, precision = correct detections / all
detections, recall = correct detections / images of the part. Writes data/bench/confidence.png.
Scenes and graphs are shared with bench/accuracy.py (data/bench/).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import CONDITIONS, part_step  # noqa: E402
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.evaluation.metrics import ModelPoints, evaluate_scene  # noqa: E402
from brepose_ros.synthetic.scenes import generate_scene  # noqa: E402
from brepose_ros.scene_folder import load_scene  # noqa: E402


def scene(step: Path, condition: str, n: int, seed: int, cache: Path):
    folder = cache / f"scene_{step.stem}_{condition}_{n}_{seed}"
    if not (folder / "gt.json").exists():
        generate_scene(step, folder, n, seed=seed, config=CONDITIONS[condition])
    return load_scene(folder)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=12)
    parser.add_argument("--part", default="sharp_bracket")
    parser.add_argument("--others", nargs="*", default=["cube", "cylinder", "sample_bracket"])
    parser.add_argument("--step-deg", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=100)
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    cache.mkdir(parents=True, exist_ok=True)
    step = part_step(args.part, cache)
    estimator = Estimator(AspectGraph.load(cached_graph_path(step, cache, args.step_deg)))
    mesh = tessellate(load_step(step))
    model = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)

    scores, correct, positive = [], [], []
    for condition in ("clean", "occl30+clutter"):
        for r in evaluate_scene(scene(step, condition, args.n, args.seed, cache), estimator, model):
            scores.append(r.estimate.score)
            correct.append(bool(r.errors and r.errors.success))
            positive.append(True)
    for other in args.others:
        other_step = part_step(other, cache)
        other_scene = scene(other_step, "clean", args.n, args.seed, cache)
        other_mesh = tessellate(load_step(other_step))
        other_model = ModelPoints.from_mesh(other_mesh.vertices, other_mesh.triangles)
        for r in evaluate_scene(other_scene, estimator, other_model):
            scores.append(r.estimate.score)
            correct.append(False)
            positive.append(False)
    estimator.close()
    scores, correct, positive = map(np.array, (scores, correct, positive))

    thresholds = np.round(np.arange(0.3, 1.0, 0.05), 2)
    print(f"{positive.sum()} images of {step.stem}, {(~positive).sum()} of other parts\n")
    print("| min_score | detections | precision | recall |")
    print("|---|---|---|---|")
    curve = []
    for th in thresholds:
        found = scores >= th
        precision = (found & correct).sum() / max(found.sum(), 1)
        recall = (found & correct).sum() / positive.sum()
        curve.append((precision, recall))
        print(f"| {th:.2f} | {found.sum()} | {precision:.2f} | {recall:.2f} |")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    p, r = np.array(curve).T
    axes[0].plot(r, p, marker="o")
    for th, x, y in zip(thresholds[::2], r[::2], p[::2]):
        axes[0].annotate(f"{th:.2f}", (x, y), fontsize=7)
    axes[0].set_xlabel("recall")
    axes[0].set_ylabel("precision")
    axes[0].set_xlim(0, 1)
    axes[0].set_ylim(0, 1.05)
    axes[0].grid(alpha=0.3)
    bins = np.linspace(0, 1, 21)
    axes[1].hist([scores[correct], scores[positive & ~correct], scores[~positive]], bins=bins, stacked=True,
                 label=["part, right pose", "part, wrong pose", "other part"],
                 color=["tab:green", "tab:orange", "tab:red"])
    axes[1].set_xlabel("score")
    axes[1].set_ylabel("images")
    axes[1].legend()
    fig.suptitle(f"score of the {step.stem} estimator")
    fig.tight_layout()
    fig.savefig(cache / "confidence.png", dpi=90)
    print(f"\nwrote {cache / 'confidence.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

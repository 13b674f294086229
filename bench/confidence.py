"""Can the score be thresholded? Precision and recall of `found` against the score, and the
calibrated `pose.min_score`.

    python bench/confidence.py [--n 12] [--parts sharp_bracket rounded_bracket ...] [--check-parts shaft ...]
                               [--params FILE.yaml] [--precision 0.95] [--plot docs/figures/precision_recall.png]

Each part's estimator sees images of its part (positives: clean, and off-centre with 20 %
occlusion among clutter), where a detection is correct when the pose succeeds (rotation
< 5 deg, translation < 5 % of the diameter), and the clean images of every *other* part
(scenes without it), where any detection is wrong. Pooled over the parts, for each
threshold on the score: precision = correct detections / all detections, recall = correct
detections / images of the part; a pose turned by an exact symmetry of the part is right.
The calibrated min_score is the lowest threshold whose
precision reaches ``--precision`` (``metrics.calibrate_min_score``), chosen on ``--parts``
(default: bench/accuracy.py's tuning set) and checked on ``--check-parts`` (leave-out parts,
measured the same way among themselves), once with every negative and once without the
images of a part's look-alike (``LOOK_ALIKES``). Scenes and graphs are shared with
bench/accuracy.py (data/bench/).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import (CONDITIONS, LOOKS, PARTS, SPAN, TUNING,  # noqa: E402
                            distractor_meshes, scene, scenes_folder, step_file)
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.figures import pyplot, save_figure  # noqa: E402
from brepose_ros.evaluation.metrics import (ModelPoints, calibrate_min_score, evaluate_scene,  # noqa: E402
                                            precision_recall)
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402
from brepose_ros.synthetic.scenes import SceneConfig  # noqa: E402

POSITIVE_CONDITIONS = ("clean", "occl20+clutter")
#: a part's look-alike: the seed paper's Fig. 7 pair, the same L body with and without
#: fillets, which no edge score tells apart at the bench's sizes (docs/results/confidence.md);
#: the threshold is calibrated with and without their images among the negatives
LOOK_ALIKES = {"sharp_bracket": "rounded_bracket", "rounded_bracket": "sharp_bracket"}


class Collector:
    """Scores of each part's estimator on its own scenes and on the other parts' clean ones."""

    def __init__(self, n: int, seed: int, step_deg: float, look: str, params: EstimatorParams, cache: Path):
        self.n, self.seed, self.step_deg, self.look, self.params, self.cache = n, seed, step_deg, look, params, cache
        self.distractors = distractor_meshes(cache)
        self.records: list[dict] = []

    def scene(self, name: str, step: Path, condition: str):
        config = SceneConfig(span=SPAN, look=self.look, **CONDITIONS[condition])
        folder = self.cache / scenes_folder(self.look, SPAN) / f"{name}_{condition}_{self.seed}"
        return scene(step, folder, self.n, self.seed, config, self.distractors)

    def collect(self, names: list[str]):
        """(scores, correct, positive, owner, part) arrays, one entry per image and estimator
        (part: whose image it is); what each estimate reported beside its score goes to
        ``self.records``."""
        steps = {name: step_file(PARTS[name], self.cache) for name in names}
        steps = {name: step for name, step in steps.items() if step is not None}
        models = {}
        for name, step in steps.items():
            mesh = tessellate(load_step(step))
            models[name] = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        scores, correct, positive, owner, part = [], [], [], [], []
        for name, step in steps.items():
            estimator = Estimator(AspectGraph.load(cached_graph_path(step, self.cache, self.step_deg)), self.params)
            for other, other_step in steps.items():
                for condition in POSITIVE_CONDITIONS if other == name else ("clean",):
                    for r in evaluate_scene(self.scene(other, other_step, condition), estimator, models[other]):
                        scores.append(r.estimate.score)
                        # a pose turned by an exact symmetry of the part is the same pose
                        correct.append(other == name and bool(r.errors and r.errors.success_sym))
                        positive.append(other == name)
                        owner.append(name)
                        part.append(other)
                        self.records.append(record(r.estimate, name, other, condition, correct[-1]))
            estimator.close()
            print(f"{name}: done", file=sys.stderr)
        return tuple(map(np.array, (scores, correct, positive, owner, part)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=12, help="images per part and condition")
    parser.add_argument("--parts", nargs="*", default=list(TUNING), choices=list(PARTS),
                        help="parts the threshold is chosen on")
    parser.add_argument("--check-parts", nargs="*", default=[], choices=list(PARTS),
                        help="parts the chosen threshold is checked on")
    parser.add_argument("--step-deg", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--look", default="varied", choices=LOOKS)
    parser.add_argument("--params", type=Path, help="estimator parameter YAML (config/estimator.yaml layout)")
    parser.add_argument("--precision", type=float, default=0.95, help="precision the min_score must reach")
    parser.add_argument("--plot", type=Path, default=REPO / "data" / "bench" / "confidence.png")
    parser.add_argument("--records", type=Path, help="write what every estimate reported to this JSON file")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    cache.mkdir(parents=True, exist_ok=True)
    params = EstimatorParams.load(args.params) if args.params else EstimatorParams()
    collector = Collector(args.n, args.seed, args.step_deg, args.look, params, cache)
    scores, correct, positive, owner, part = collector.collect(args.parts)

    thresholds = np.round(np.arange(0.3, 1.0, 0.05), 2)
    precision, recall, detections = precision_recall(scores, correct, positive.sum(), thresholds)
    print(f"{positive.sum()} images with the part, {(~positive).sum()} without it ({', '.join(args.parts)}; "
          f"graphs at {args.step_deg:g} deg, {args.look} look, min_score of --params ignored)\n")
    print("| min_score | detections | precision | recall |")
    print("|---|---|---|---|")
    for th, d, p, r in zip(thresholds, detections, precision, recall):
        print(f"| {th:.2f} | {d} | {p:.2f} | {r:.2f} |")
    calibrated = calibrate_min_score(scores, correct, args.precision)
    if calibrated is None:
        print(f"\nno threshold reaches precision {args.precision}")
    else:
        (p,), (r,), (d,) = precision_recall(scores, correct, positive.sum(), [calibrated])
        print(f"\ncalibrated min_score {calibrated:.3f}: precision {p:.3f}, recall {r:.3f}, {d} detections")
    print("\n| part | right poses | calibrated min_score alone |\n|---|---|---|")
    for name in dict.fromkeys(owner):
        mine = owner == name
        alone = calibrate_min_score(scores[mine], correct[mine], args.precision)
        print(f"| {name} | {correct[mine].sum()} of {positive[mine].sum()} | "
              f"{'none' if alone is None else f'{alone:.3f}'} |")
    # the same calibration without a look-alike's images among the negatives
    apart = np.array([LOOK_ALIKES.get(o) != p for o, p in zip(owner, part)])
    calibrated_apart = calibrate_min_score(scores[apart], correct[apart], args.precision)
    if apart.all():
        calibrated_apart = None  # no look-alike among the parts: the same as above
    elif calibrated_apart is None:
        print(f"\nwithout the look-alikes' images: no threshold reaches precision {args.precision}")
    else:
        (p,), (r,), (d,) = precision_recall(scores[apart], correct[apart], positive.sum(), [calibrated_apart])
        print(f"\nwithout the look-alikes' images ({(~apart).sum()} estimates left out): calibrated min_score "
              f"{calibrated_apart:.3f}: precision {p:.3f}, recall {r:.3f}, {d} detections")
    curves = {"tuning parts": (scores, correct, positive.sum())}
    if not apart.all():
        curves["tuning parts, look-alikes left out"] = (scores[apart], correct[apart], positive.sum())
    chosen = [th for th in (calibrated, calibrated_apart) if th is not None]
    if args.check_parts:
        s, c, pos, _, _ = collector.collect(args.check_parts)
        curves["leave-out parts"] = (s, c, pos.sum())
        for th in chosen:
            (p,), (r,), (d,) = precision_recall(s, c, pos.sum(), [th])
            print(f"\nchecked on {', '.join(args.check_parts)} ({pos.sum()} images with the part, {(~pos).sum()} "
                  f"without): at {th:.3f} precision {p:.3f}, recall {r:.3f}, {d} detections")
    if args.records:
        args.records.parent.mkdir(parents=True, exist_ok=True)
        args.records.write_text(json.dumps(collector.records, indent=1) + "\n")
    plot(args.plot, curves, scores, correct, positive, calibrated_apart or calibrated, args.precision)
    print(f"\nwrote {args.plot}")
    return 0


def record(estimate, owner: str, part: str, condition: str, correct: bool) -> dict:
    """What one estimate reported, for fitting and checking a confidence on it."""
    shares = estimate.shares._asdict() if estimate.shares is not None else {}
    return dict(owner=owner, part=part, condition=condition, correct=correct, score=float(estimate.score),
                error_ratio=float(estimate.error_ratio), margin=estimate.symmetry_margin,
                ambiguous=bool(estimate.ambiguous), **shares)


def plot(path: Path, curves: dict, scores, correct, positive, calibrated, target) -> None:
    """Precision against recall of each of ``curves`` (label -> scores, correct, images with
    the part) with the calibrated threshold marked, and the first's scores by outcome."""
    plt = pyplot()

    fine = np.linspace(0.0, 1.0, 101)
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 3.6))
    for label, (s, c, n_positive) in curves.items():
        precision, recall, _ = precision_recall(s, c, n_positive, fine)
        axes[0].plot(recall, precision, marker=".", markersize=3, label=label)
        for th in (0.6, 0.7, 0.8, 0.9):
            i = int(round(th * 100))
            axes[0].annotate(f"{th:.1f}", (recall[i], precision[i]), fontsize=7)
    axes[0].axhline(target, color="grey", linestyle=":", linewidth=1)
    if calibrated is not None:
        for n, (s, c, n_positive) in enumerate(curves.values()):
            (p,), (r,), _ = precision_recall(s, c, n_positive, [calibrated])
            axes[0].plot([r], [p], "r*", markersize=9, label=None if n else f"min_score {calibrated:.3f}")
    axes[0].legend(fontsize=7, loc="lower left")
    axes[0].set_xlabel("recall")
    axes[0].set_ylabel("precision")
    axes[0].set_xlim(0, 1)
    axes[0].set_ylim(0, 1.05)
    axes[0].grid(alpha=0.3)
    bins = np.linspace(0, 1, 21)
    axes[1].hist([scores[correct], scores[positive & ~correct], scores[~positive]], bins=bins, stacked=True,
                 label=["part, right pose", "part, wrong pose", "part absent"],
                 color=["tab:green", "tab:orange", "tab:red"])
    if calibrated is not None:
        axes[1].axvline(calibrated, color="k", linestyle="--", linewidth=1)
    axes[1].set_xlabel("score")
    axes[1].set_ylabel("images")
    axes[1].legend(fontsize=8)
    axes[1].set_title(f"{next(iter(curves))}", fontsize=9)
    fig.suptitle("score against correctness, pooled over the parts", fontsize=10)
    save_figure(fig, path, dpi=72)


if __name__ == "__main__":
    sys.exit(main())

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
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.accuracy import (LOOKS, PARTS, SPAN, TUNING,  # noqa: E402
                            distractor_meshes, scene, step_file)
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.figures import pyplot, save_figure  # noqa: E402
from brepose_ros.evaluation.metrics import (ModelPoints, calibrate_min_score, evaluate_scene,  # noqa: E402
                                            precision_recall)
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros import __version__  # noqa: E402
from brepose_ros.online.confidence import FEATURES, SHIPPED, Calibration, features  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402

POSITIVE_CONDITIONS = ("clean", "occl20+clutter")
#: a part's look-alike: the seed paper's Fig. 7 pair, the same L body with and without
#: fillets, which no edge score tells apart at the bench's sizes (docs/results/confidence.md);
#: the threshold is calibrated with and without their images among the negatives
LOOK_ALIKES = {"sharp_bracket": "rounded_bracket", "rounded_bracket": "sharp_bracket"}
#: the lead's first probe of a confidence (session 8): the score, its parts, the error ratio
#: and the twin check, without the projection's size and the image's line count
PROBE_FEATURES = ("score", "error_ratio", "confirmed", "explained", "log_insignificance", "twin_margin", "ambiguous")
#: the fit's default L2 weight on the standardised weights
L2 = 0.01
#: the found rules on the confidence reported
MIN_CONFIDENCES = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8)
CALIBRATION_HEADER = """The confidence of brepose_ros (online/confidence.py): a logistic model of the probability
that an estimate's pose is right, fitted by bench/confidence.py --fit on the tuning parts' scenes
with and without the part (provenance below). The checksum covers the numbers and the
provenance: edit nothing by hand, fit again."""


class Collector:
    """What each part's estimator reports on its own scenes and on the other parts' clean ones."""

    def __init__(self, n: int, seed: int, step_deg: float, look: str, params: EstimatorParams, cache: Path):
        self.n, self.seed, self.step_deg, self.look, self.params, self.cache = n, seed, step_deg, look, params, cache
        self.distractors = distractor_meshes(cache)

    def scene(self, name: str, step: Path, condition: str):
        return scene(self.cache, name, step, condition, self.n, self.distractors, self.look, SPAN, self.seed)

    def collect(self, names: list[str]) -> list[dict]:
        """One ``record`` per image and estimator of ``names`` (owner: the estimator's part,
        part: whose image it is)."""
        steps = {name: step_file(PARTS[name], self.cache) for name in names}
        steps = {name: step for name, step in steps.items() if step is not None}
        models = {}
        for name, step in steps.items():
            mesh = tessellate(load_step(step))
            models[name] = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
        records = []
        for name, step in steps.items():
            estimator = Estimator(AspectGraph.load(cached_graph_path(step, self.cache, self.step_deg)), self.params)
            for other, other_step in steps.items():
                for condition in POSITIVE_CONDITIONS if other == name else ("clean",):
                    for r in evaluate_scene(self.scene(other, other_step, condition), estimator, models[other]):
                        # a pose turned by an exact symmetry of the part is the same pose
                        correct = other == name and bool(r.errors and r.errors.success_sym)
                        records.append(record(r.estimate, name, other, condition, correct))
            estimator.close()
            print(f"{name}: done", file=sys.stderr)
        return records


def arrays(records: list[dict]):
    """(scores, correct, positive, owner, part) arrays of records."""
    return (np.array([r["score"] for r in records]), np.array([r["correct"] for r in records], bool),
            np.array([r["owner"] == r["part"] for r in records], bool), np.array([r["owner"] for r in records]),
            np.array([r["part"] for r in records]))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=12, help="images per part and condition")
    parser.add_argument("--parts", nargs="*", default=list(TUNING), choices=list(PARTS),
                        help="parts the threshold and the confidence are chosen on")
    parser.add_argument("--check-parts", nargs="*", default=[], choices=list(PARTS),
                        help="parts the chosen threshold and confidence are checked on")
    parser.add_argument("--step-deg", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--look", default="varied", choices=LOOKS)
    parser.add_argument("--params", type=Path, help="estimator parameter YAML (config/estimator.yaml layout)")
    parser.add_argument("--precision", type=float, default=0.95, help="precision the min_score must reach")
    parser.add_argument("--plot", type=Path, default=REPO / "data" / "bench" / "confidence.png")
    parser.add_argument("--records", type=Path, help="write what every estimate reported to this JSON file")
    parser.add_argument("--from-records", type=Path,
                        help="read the estimates of --parts and --check-parts from a --records file instead of "
                             "running the estimator")
    parser.add_argument("--fit", type=Path, metavar="FILE",
                        help="fit the confidence on --parts' estimates and write its calibration here (the "
                             f"shipped one is brepose_ros/{SHIPPED})")
    parser.add_argument("--features", nargs="+", default=list(FEATURES), choices=list(FEATURES),
                        help="features of the fitted confidence")
    parser.add_argument("--l2", type=float, default=L2, help="L2 weight of the fit (standardised features)")
    parser.add_argument("--confidence-plot", type=Path, default=REPO / "data" / "bench" / "confidence_vs_score.png")
    args = parser.parse_args(argv)
    cache = REPO / "data" / "bench"
    cache.mkdir(parents=True, exist_ok=True)
    params = EstimatorParams.load(args.params) if args.params else EstimatorParams()
    if args.from_records:
        stored = json.loads(args.from_records.read_text())
        tuning = [r for r in stored if r["owner"] in args.parts and r["part"] in args.parts]
        checked = [r for r in stored if r["owner"] in args.check_parts and r["part"] in args.check_parts]
    else:
        collector = Collector(args.n, args.seed, args.step_deg, args.look, params, cache)
        tuning = collector.collect(args.parts)
        checked = collector.collect(args.check_parts) if args.check_parts else []
    if args.records:
        args.records.parent.mkdir(parents=True, exist_ok=True)
        args.records.write_text(json.dumps(tuning + checked, indent=1) + "\n")
    scores, correct, positive, owner, part = arrays(tuning)

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
    if checked:
        s, c, pos, _, _ = arrays(checked)
        curves["leave-out parts"] = (s, c, pos.sum())
        for th in chosen:
            (p,), (r,), (d,) = precision_recall(s, c, pos.sum(), [th])
            print(f"\nchecked on {', '.join(args.check_parts)} ({pos.sum()} images with the part, {(~pos).sum()} "
                  f"without): at {th:.3f} precision {p:.3f}, recall {r:.3f}, {d} detections")
    plot(args.plot, curves, scores, correct, positive, calibrated_apart or calibrated, args.precision)
    print(f"\nwrote {args.plot}")
    calibration = fit_confidence(tuning, tuple(args.features), args.l2, args)
    report_confidence(calibration, tuning, checked, args)
    return 0


def fit_confidence(tuning: list[dict], names: tuple[str, ...], l2: float, args) -> Calibration:
    """The confidence fitted on the tuning parts' estimates, written to ``--fit`` with its
    provenance; the choice of features and L2 weight shown by leave-one-part-out."""
    x, y = feature_matrix(tuning, names), np.array([r["correct"] for r in tuning], bool)
    owners = np.array([r["owner"] for r in tuning])
    print(f"\nconfidence fitted on {len(y)} estimates of {', '.join(args.parts)} ({y.sum()} right): "
          "average precision of each part's estimates under the fit on the other parts")
    print("\n| features | L2 | " + " | ".join(dict.fromkeys(owners)) + " | pooled |\n|---|---|" +
          "---|" * (len(set(owners)) + 1))
    for set_name, chosen in (("probe", PROBE_FEATURES), ("all", tuple(FEATURES)), ("--features", names)):
        for weight in sorted({L2, 0.1, l2}):
            held = np.zeros(len(y))
            cells = []
            for name in dict.fromkeys(owners):
                mine = owners == name
                held[mine] = Calibration.fit(feature_matrix(tuning, chosen)[~mine], y[~mine], chosen,
                                             weight).logit(feature_matrix(tuning, chosen)[mine])
                cells.append(f"{average_precision(held[mine], y[mine]):.2f}")
            print(f"| {set_name} | {weight:g} | " + " | ".join(cells) + f" | {average_precision(held, y):.2f} |")
    score = np.array([r["score"] for r in tuning])
    print("| score alone | | " + " | ".join(f"{average_precision(score[owners == n], y[owners == n]):.2f}"
                                          for n in dict.fromkeys(owners)) + f" | {average_precision(score, y):.2f} |")
    provenance = {"parts": list(args.parts), "scenes": f"{args.n} images per part and condition "
                  f"({', '.join(POSITIVE_CONDITIONS)} of the part, clean of the other parts), seed {args.seed}, "
                  f"{args.look} look, graphs at {args.step_deg:g} deg",
                  "estimates": int(len(y)), "right": int(y.sum()), "l2": l2, "version": __version__,
                  "commit": git_commit(), "command": "python bench/confidence.py " + " ".join(sys.argv[1:])}
    calibration = Calibration.fit(x, y, names, l2, provenance)
    if args.fit:
        calibration.save(args.fit, CALIBRATION_HEADER)
        calibration = Calibration.load(args.fit)
        print(f"\nwrote {args.fit}")
    print("\n| feature | weight (standardised) |\n|---|---|")
    for name, w in zip(calibration.features, calibration.weights):
        print(f"| {name} | {w:+.2f} |")
    print(f"| (bias) | {calibration.bias:+.2f} |")
    return calibration


def report_confidence(calibration: Calibration, tuning: list[dict], checked: list[dict], args) -> None:
    """Score against the fitted confidence as a found rule, on the tuning parts and on the
    leave-out parts (never fitted on), and their precision-recall curves."""
    curves = {}
    print("\n| set | ranking | average precision | recall at precision >= 0.9 | recall at >= 0.95 |\n"
          "|---|---|---|---|---|")
    for label, records in (("tuning parts", tuning), ("leave-out parts", checked)):
        if not records:
            continue
        scores, correct, positive, _, _ = arrays(records)
        confidence = calibration.probability(feature_matrix(records, calibration.features))
        for ranking, values in (("score", scores), ("confidence", confidence)):
            curves[f"{label}, {ranking}"] = (values, correct, positive.sum())
            cells = []
            for target in (0.9, 0.95):
                th = calibrate_min_score(values, correct, target)
                cells.append("none" if th is None else
                             f"{precision_recall(values, correct, positive.sum(), [th])[1][0]:.2f} (at {th:.2f})")
            print(f"| {label} | {ranking} | {average_precision(values, correct):.2f} | " + " | ".join(cells) + " |")
    for label, records in (("tuning parts", tuning), ("leave-out parts", checked)):
        if not records:
            continue
        scores, correct, positive, _, _ = arrays(records)
        confidence = calibration.probability(feature_matrix(records, calibration.features))
        print(f"\n{label} ({positive.sum()} images with the part, {correct.sum()} right poses, "
              f"{len(records)} estimates): found rules\n\n| rule | detections | right | precision | recall |\n"
              "|---|---|---|---|---|")
        rules = {"score >= 0.6 (today)": scores >= 0.6}
        for th in MIN_CONFIDENCES:
            rules[f"confidence >= {th:g}"] = confidence >= th
            rules[f"score >= 0.6 and confidence >= {th:g}"] = (scores >= 0.6) & (confidence >= th)
        for rule, found in rules.items():
            right = int((found & correct).sum())
            print(f"| {rule} | {found.sum()} | {right} | {right / max(found.sum(), 1):.2f} | "
                  f"{right / max(positive.sum(), 1):.2f} |")
        edges = np.linspace(0, 1, 6)
        bins = np.clip(np.digitize(confidence, edges) - 1, 0, 4)
        print("\n| confidence | estimates | right (share) |\n|---|---|---|")
        for b in range(5):
            mine = bins == b
            print(f"| {edges[b]:.1f}-{edges[b + 1]:.1f} | {mine.sum()} | "
                  f"{correct[mine].sum()} ({correct[mine].mean() if mine.any() else float('nan'):.2f}) |")
    plot_confidence(args.confidence_plot, curves)
    print(f"\nwrote {args.confidence_plot}")


def feature_matrix(records: list[dict], names) -> np.ndarray:
    return np.array([[r[name] for name in names] for r in records], float).reshape(len(records), len(names))


def average_precision(values, correct) -> float:
    """Mean, over the right estimates, of the precision of the estimates ranked at or above
    each (ranked by ``values``, highest first): 1 when every right pose outranks every wrong one."""
    values, correct = np.asarray(values, float), np.asarray(correct, bool)
    if not correct.any():
        return float("nan")
    order = np.argsort(-values, kind="stable")
    hits = np.cumsum(correct[order])
    return float(np.mean((hits / np.arange(1, len(values) + 1))[correct[order]]))


def git_commit() -> str:
    try:
        return subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def record(estimate, owner: str, part: str, condition: str, correct: bool) -> dict:
    """What one estimate reported, for fitting and checking a confidence on it: the
    features of ``confidence.FEATURES`` and the confidence of the estimator's calibration."""
    shares = estimate.shares._asdict() if estimate.shares is not None else {}
    return {"owner": owner, "part": part, "condition": condition, "correct": correct,
            "margin": estimate.symmetry_margin, "confidence": float(estimate.confidence), **shares,
            **features(estimate)}


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


def plot_confidence(path: Path, curves: dict) -> None:
    """Precision against recall of the score and of the confidence (``curves``: label ->
    values, correct, images with the part), with the found rules in use marked."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(5.2, 4.0))
    styles = {"tuning parts": ":", "leave-out parts": "-"}
    for label, (values, correct, n_positive) in curves.items():
        grid = np.unique(np.concatenate([values, [np.inf]]))
        precision, recall, _ = precision_recall(values, correct, n_positive, grid)
        kind = label.split(", ")[1]
        ax.plot(recall, precision, styles[label.split(", ")[0]], color="tab:blue" if kind == "score" else "tab:red",
                label=label)
        th = 0.6 if kind == "score" else 0.5
        (p,), (r,), _ = precision_recall(values, correct, n_positive, [th])
        ax.plot([r], [p], "o", color="tab:blue" if kind == "score" else "tab:red", markersize=5)
        ax.annotate(f"{kind} {th:g}", (r, p), fontsize=7, xytext=(4, -8), textcoords="offset points")
    ax.axhline(0.95, color="grey", linestyle=":", linewidth=1)
    ax.set_xlabel("recall (right poses found / images of the part)")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.05)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower left")
    ax.set_title("score against the fitted confidence", fontsize=9)
    save_figure(fig, path, dpi=72)


if __name__ == "__main__":
    sys.exit(main())

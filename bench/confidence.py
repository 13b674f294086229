"""Can the score be thresholded, and which found rule? Precision and recall of `found`
against the score, the fitted confidence, and the found rule chosen on them.

    python bench/confidence.py [--n 8] [--parts sharp_bracket rounded_bracket ...] [--check-parts shaft ...]
                               [--params FILE.yaml] [--records FILE.json | --from-records FILE.json ...]
                               [--fit brepose_ros/confidence.yaml | --calibration brepose_ros/confidence.yaml]
                               [--confidence-plot docs/figures/found_rule.png]

Each part's estimator sees images of its part (positives: clean, and off-centre with 20, 30
and 50 % occlusion among clutter), where a detection is correct when the pose succeeds
(rotation < 5 deg, translation < 5 % of the diameter; a pose turned by an exact symmetry
of the part is right), and the clean and occl30+clutter images of every *other* part
(scenes without it), where any detection is wrong; the estimator reports every pose
scoring ``RECORD_FLOOR`` or more, so that rules with a lower floor than today's can be
judged. Pooled over the parts: precision = correct detections / all detections, recall =
correct detections / images of the part.

Printed, on ``--parts`` (default: bench/accuracy.py's tuning set) and checked on
``--check-parts`` (leave-out parts, measured the same way among themselves): the calibrated
min_score (the lowest score threshold whose precision reaches ``--precision``); the
confidence (``online/confidence.py``) fitted on ``--parts`` alone (``--fit`` writes it);
the found rule (``pose.min_score``, ``pose.min_confidence``) chosen on ``--parts`` as the
one finding the most right poses with recall and precision at least today's (score >=
0.6), the trusted rule at its floor (``TRUSTED_PRECISION``), its trade curve, and the
confidence's calibration at several shares of images holding the part (``pose.prior``).
Refit after any change to what the estimator finds:

    nice -n 5 python bench/confidence.py --n 24 --check-parts motor1_holder shaft flange \
        --records docs/results/confidence_records.json --fit brepose_ros/confidence.yaml \
        --features score confirmed explained log_insignificance error_ratio twin_margin ambiguous log_size \
        log_model_length run_on shading_fit --confidence-plot docs/figures/found_rule.png \
        --plot docs/figures/precision_recall.png

and set the printed rule in brepose_ros/params.py. Scenes and graphs are shared with
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

from bench.accuracy import (CONDITIONS, LOOKS, PARTS, SPAN, TUNING,  # noqa: E402
                            distractor_meshes, scene, step_file)
from bench.graphs import cached_graph_path  # noqa: E402
from brepose_ros.aspect_graph import AspectGraph  # noqa: E402
from brepose_ros.evaluation.figures import pyplot, save_figure  # noqa: E402
from brepose_ros.evaluation.metrics import (ModelPoints, calibrate_min_score, evaluate_scene,  # noqa: E402
                                            precision_lower_bound, precision_recall, reliability)
from brepose_ros.offline.cad import load_step, tessellate  # noqa: E402
from brepose_ros import __version__  # noqa: E402
from brepose_ros.online.confidence import FEATURES, SHIPPED, Calibration, features  # noqa: E402
from brepose_ros.online.estimator import Estimator  # noqa: E402
from brepose_ros.params import EstimatorParams  # noqa: E402

#: the part's own scenes (positives) and the other parts' scenes (negatives: any pose is wrong);
#: occluded ones on both sides, so that the confidence is fitted and checked where the part is
#: partly hidden and where clutter, not the part, is in view
POSITIVE_CONDITIONS = ("clean", "occl20+clutter", "occl30+clutter", "occl50+clutter")
NEGATIVE_CONDITIONS = ("clean", "occl30+clutter")
#: the estimator reports every pose scoring this or more while recording, so that the
#: correctness of poses below today's pose.min_score is known (found rules with a lower floor)
RECORD_FLOOR = 0.3
#: a part's look-alike: the seed paper's Fig. 7 pair, the same L body with and without
#: fillets, which no edge score tells apart at the bench's sizes (docs/results/confidence.md);
#: the threshold is calibrated with and without their images among the negatives
LOOK_ALIKES = {"sharp_bracket": "rounded_bracket", "rounded_bracket": "sharp_bracket"}
#: the lead's first probe of a confidence (session 8): the score, its parts, the error ratio
#: and the twin check, without the projection's size and the image's line count
PROBE_FEATURES = ("score", "error_ratio", "confirmed", "explained", "log_insignificance", "twin_margin", "ambiguous")
#: the fit's default L2 weight on the standardised weights
L2 = 0.01
#: today's found rule before this bench chose one: score >= 0.6
TODAY = 0.6
#: the share of reported poses that must be right where a wrong pose costs more than a missed
#: one (issue 14): the trusted rule's pose.min_confidence reaches it on the tuning parts, the
#: look-alikes' images left out (no edge tells the brackets apart: a cell with both in view
#: calibrates on its own images)
TRUSTED_PRECISION = 0.95
#: the found rules tried: pose.min_score (the score's floor) and pose.min_confidence
FLOORS = (0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6)
LEVELS = tuple(float(v) for v in np.round(np.r_[np.arange(0.01, 0.1, 0.01), np.arange(0.1, 0.95, 0.05)], 2))
#: shares of images holding the part at which the confidence's calibration is shown
PRIORS = (0.2, 0.5, 1.0)
CALIBRATION_HEADER = """The confidence of brepose_ros (online/confidence.py): logistic models of whether the part is
in view and whether the pose is right where it is, whose product is the probability that an
estimate's pose is right, fitted by bench/confidence.py --fit on the tuning parts' scenes with
and without the part (provenance below; prior: the share of those images holding the part).
The checksum covers the numbers and the provenance: edit nothing by hand, fit again."""


class Collector:
    """What each part's estimator reports on its own scenes (``positives``: conditions) and on
    the other parts' (``NEGATIVE_CONDITIONS``), images ``images`` of each."""

    def __init__(self, images: range, seed: int, step_deg: float, look: str, params: EstimatorParams, cache: Path,
                 positives: tuple[str, ...] = POSITIVE_CONDITIONS):
        self.images, self.seed, self.step_deg, self.look, self.cache = images, seed, step_deg, look, cache
        self.positives = positives
        self.params = params.with_flat({"pose.min_score": RECORD_FLOOR, "pose.min_confidence": 0.0})
        self.distractors = distractor_meshes(cache)

    def scene(self, name: str, step: Path, condition: str):
        return scene(self.cache, name, step, condition, self.images, self.distractors, self.look, SPAN, self.seed)

    def collect(self, names: list[str]) -> list[dict]:
        """One ``record`` per image and estimator of ``names`` (owner: the estimator's part,
        part: whose image it is)."""
        steps = {name: step_file(PARTS[name], self.cache) for name in names}
        steps = {name: step for name, step in steps.items() if step is not None}
        models, centres = {}, {}
        for name, step in steps.items():
            mesh = tessellate(load_step(step))
            models[name] = ModelPoints.from_mesh(mesh.vertices, mesh.triangles)
            centres[name] = (mesh.vertices.min(axis=0) + mesh.vertices.max(axis=0)) / 2
        records = []
        for name, step in steps.items():
            estimator = Estimator(AspectGraph.load(cached_graph_path(step, self.cache, self.step_deg)), self.params)
            for other, other_step in steps.items():
                for condition in self.positives if other == name else NEGATIVE_CONDITIONS:
                    scene = self.scene(other, other_step, condition)
                    for entry, r in zip(scene.entries, evaluate_scene(scene, estimator, models[other])):
                        # a pose turned by an exact symmetry of the part is the same pose
                        correct = other == name and bool(r.errors and r.errors.success_sym)
                        records.append(record(r, name, other, condition, correct,
                                              float(np.linalg.norm(entry.R @ centres[other] + entry.t))))
            estimator.close()
            print(f"{name}: done", file=sys.stderr)
        return records


def apart_from_look_alikes(owner: np.ndarray, part: np.ndarray) -> np.ndarray:
    """Which estimates are not of a part's estimator on its look-alike's image."""
    return np.array([LOOK_ALIKES.get(o) != p for o, p in zip(owner, part)], bool)


def arrays(records: list[dict]):
    """(scores, correct, positive, owner, part) arrays of records."""
    return (np.array([r["score"] for r in records]), np.array([r["correct"] for r in records], bool),
            np.array([r["owner"] == r["part"] for r in records], bool), np.array([r["owner"] for r in records]),
            np.array([r["part"] for r in records]))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=8, help="images per part and condition")
    parser.add_argument("--start", type=int, default=0,
                        help="first image of each scene: --start 12 checks a fit on images it did not see")
    parser.add_argument("--positives", nargs="+", default=list(POSITIVE_CONDITIONS), choices=list(CONDITIONS),
                        help="conditions of the part's own scenes")
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
    parser.add_argument("--from-records", type=Path, nargs="+", metavar="FILE",
                        help="read the estimates of --parts and --check-parts from --records files (pooled) "
                             "instead of running the estimator")
    parser.add_argument("--fit", type=Path, metavar="FILE",
                        help="fit the confidence on --parts' estimates and write its calibration here (the "
                             f"shipped one is brepose_ros/{SHIPPED})")
    parser.add_argument("--calibration", type=Path, metavar="FILE",
                        help="judge this calibration (e.g. the shipped brepose_ros/confidence.yaml) on the estimates "
                             "instead of fitting one: found rules, trusted rule, reliability and --confidence-plot")
    parser.add_argument("--features", nargs="+", default=list(FEATURES), choices=list(FEATURES),
                        help="features of the fitted confidence")
    parser.add_argument("--l2", type=float, default=L2, help="L2 weight of the fit (standardised features)")
    parser.add_argument("--confidence-plot", type=Path, default=REPO / "data" / "bench" / "found_rule.png",
                        help="found rules (precision against recall) and the confidence's reliability")
    args = parser.parse_args(argv)
    if args.calibration and args.fit:
        parser.error("--calibration judges a fit, --fit makes one: give one of them")
    cache = REPO / "data" / "bench"
    cache.mkdir(parents=True, exist_ok=True)
    params = EstimatorParams.load(args.params) if args.params else EstimatorParams()
    if args.from_records:
        stored = [r for path in args.from_records for r in json.loads(path.read_text())]
        tuning = [r for r in stored if r["owner"] in args.parts and r["part"] in args.parts]
        checked = [r for r in stored if r["owner"] in args.check_parts and r["part"] in args.check_parts]
    else:
        collector = Collector(range(args.start, args.start + args.n), args.seed, args.step_deg, args.look, params,
                              cache, tuple(args.positives))
        tuning = collector.collect(args.parts)
        checked = collector.collect(args.check_parts) if args.check_parts else []
    if args.records:
        args.records.parent.mkdir(parents=True, exist_ok=True)
        # one estimate a line, as a scene's gt.json: 3,072 estimates (64 images) in 2.6 MB, not 3
        args.records.write_text("[\n" + ",\n".join(json.dumps(r) for r in tuning + checked) + "\n]\n")
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
    apart = apart_from_look_alikes(owner, part)
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
    if args.calibration:
        calibration = Calibration.load(args.calibration)
        print(f"\nthe calibration of {args.calibration}, fitted on {calibration.provenance.get('commit', '?')}")
    else:
        calibration = fit_confidence(tuning, tuple(args.features), args.l2, args)
    report_confidence(calibration, tuning, checked, args)
    return 0


def fit_confidence(tuning: list[dict], names: tuple[str, ...], l2: float, args) -> Calibration:
    """The confidence fitted on the tuning parts' estimates, written to ``--fit`` with its
    provenance; the choice of features and L2 weight shown by leave-one-part-out."""
    x, y = feature_matrix(tuning, names), np.array([r["correct"] for r in tuning], bool)
    present = np.array([r["owner"] == r["part"] for r in tuning], bool)
    owners = np.array([r["owner"] for r in tuning])
    print(f"\nconfidence fitted on {len(y)} estimates of {', '.join(args.parts)} ({y.sum()} right, "
          f"{present.sum()} of images holding the part): average precision of each part's estimates under the "
          "fit on the other parts")
    print("\n| features | L2 | " + " | ".join(dict.fromkeys(owners)) + " | pooled |\n|---|---|" +
          "---|" * (len(set(owners)) + 1))
    for set_name, chosen in (("probe", PROBE_FEATURES), ("all", tuple(FEATURES)), ("--features", names)):
        for weight in sorted({L2, 0.1, l2}):
            held = np.zeros(len(y))
            cells = []
            for name in dict.fromkeys(owners):
                mine = owners == name
                held[mine] = Calibration.fit(feature_matrix(tuning, chosen)[~mine], y[~mine], present[~mine], chosen,
                                             weight).probability(feature_matrix(tuning, chosen)[mine])
                cells.append(f"{average_precision(held[mine], y[mine]):.2f}")
            print(f"| {set_name} | {weight:g} | " + " | ".join(cells) + f" | {average_precision(held, y):.2f} |")
    score = np.array([r["score"] for r in tuning])
    print("| score alone | | " + " | ".join(f"{average_precision(score[owners == n], y[owners == n]):.2f}"
                                          for n in dict.fromkeys(owners)) + f" | {average_precision(score, y):.2f} |")
    provenance = {"parts": list(args.parts), "scenes": f"{args.n} images per part and condition "
                  f"({', '.join(args.positives)} of the part; {', '.join(NEGATIVE_CONDITIONS)} of the other "
                  f"parts), seed {args.seed}, {args.look} look, graphs at {args.step_deg:g} deg" +
                  (f", images from {args.start}" if args.start else ""),
                  "estimates": int(len(y)), "right": int(y.sum()), "l2": l2, "version": __version__,
                  "commit": git_commit(), "command": "python bench/confidence.py " + " ".join(sys.argv[1:])}
    calibration = Calibration.fit(x, y, present, names, l2, provenance)
    if args.fit:
        calibration.save(args.fit, CALIBRATION_HEADER)
        calibration = Calibration.load(args.fit)
        print(f"\nwrote {args.fit}")
    print(f"\nfitted at prior {calibration.prior:.2f} (share of the estimates' images holding the part)\n\n"
          "| feature | weight: part in view | weight: pose right where it is |\n|---|---|---|")
    for name, a, b in zip(calibration.features, calibration.present.weights, calibration.right.weights):
        print(f"| {name} | {a:+.2f} | {b:+.2f} |")
    print(f"| (bias) | {calibration.present.bias:+.2f} | {calibration.right.bias:+.2f} |")
    return calibration


class Outcomes:
    """A set of estimates as found rules see them: score, confidence at ``prior``, right,
    whether the image holds the part, and its condition."""

    def __init__(self, records: list[dict], calibration: Calibration, prior: float | None = None):
        self.score, self.correct, self.positive, owner, part = arrays(records)
        self.confidence = calibration.probability(feature_matrix(records, calibration.features), prior, tied(records))
        self.condition = np.array([r["condition"] for r in records])
        self.apart = apart_from_look_alikes(owner, part)

    def rule(self, floor: float, level: float, among=None) -> tuple[int, int, float, float]:
        """Found (score >= floor and confidence >= level): detections, right ones, precision
        (right / detections, 1 when none) and recall (right / images with the part), over
        the estimates ``among`` (a mask; default all)."""
        among = np.ones(len(self.score), bool) if among is None else among
        found = (self.score >= floor) & (self.confidence >= level) & among
        right = int((found & self.correct).sum())
        n = int(found.sum())
        return n, right, right / n if n else 1.0, right / max(int((self.positive & among).sum()), 1)


def choose_rule(outcomes: Outcomes) -> tuple[float, float] | None:
    """The (floor, level) of ``FLOORS`` x ``LEVELS`` with the most right poses found among
    those whose recall and precision are both at least today's rule's (score >= TODAY), the
    higher precision on a tie; None if none is."""
    _, _, today_p, today_r = outcomes.rule(TODAY, 0.0)
    best, key = None, None
    for floor in FLOORS:
        for level in LEVELS:
            _, right, p, r = outcomes.rule(floor, level)
            if p >= today_p and r >= today_r and (key is None or (right, p) > key):
                best, key = (floor, float(level)), (right, p)
    return best


def report_confidence(calibration: Calibration, tuning: list[dict], checked: list[dict], args) -> None:
    """Score against the fitted confidence: ranking, found rules (chosen on the tuning
    parts, checked on the leave-out parts, never fitted on), and calibration at several
    shares of images holding the part."""
    sets = {"tuning parts": tuning, "leave-out parts": checked} if checked else {"tuning parts": tuning}
    print("\n| set | ranking | average precision | recall at precision >= 0.9 | recall at >= 0.95 |\n"
          "|---|---|---|---|---|")
    for label, records in sets.items():
        o = Outcomes(records, calibration)
        for ranking, values in (("score", o.score), ("confidence", o.confidence)):
            cells = []
            for target in (0.9, 0.95):
                th = calibrate_min_score(values, o.correct, target)
                cells.append("none" if th is None else
                             f"{precision_recall(values, o.correct, o.positive.sum(), [th])[1][0]:.2f} (at {th:.2f})")
            print(f"| {label} | {ranking} | {average_precision(values, o.correct):.2f} | " + " | ".join(cells) + " |")
    outcomes = {label: Outcomes(records, calibration) for label, records in sets.items()}
    chosen = choose_rule(outcomes["tuning parts"])
    print(f"\nfound rule chosen on the tuning parts (most right poses with recall and precision at least "
          f"score >= {TODAY:g}'s): " + ("none" if chosen is None else
                                        f"pose.min_score {chosen[0]:g}, pose.min_confidence {chosen[1]:g}"))
    tuning = outcomes["tuning parts"]
    trusted = None if chosen is None else choose_rule_at(tuning, chosen[0], TRUSTED_PRECISION, tuning.apart)
    if chosen is not None:
        print(f"trusted rule (at that floor, most right poses with precision >= {TRUSTED_PRECISION:g} on the tuning "
              "parts, look-alikes' images left out): " +
              ("none" if trusted is None else f"pose.min_confidence {trusted:g}"))
    if trusted is not None:
        # the level is chosen on a few tens of poses: say what precision they support
        for label, o, among in (("tuning parts, look-alikes' images left out", tuning, tuning.apart), *(
                (label, outcomes[label], None) for label in sets if label != "tuning parts")):
            found, right, _, _ = o.rule(chosen[0], trusted, among)
            print(f"  {label}: {right} of {found} right, precision at least "
                  f"{precision_lower_bound(right, found):.2f} (Wilson 95 % interval)")
    header = " | ".join(f"{label}: found, right, precision, recall" for label in sets)
    print(f"\n| rule | {header} |\n|---|" + "---|" * len(sets))

    def row(name, floor, level, among=None):
        cells = [outcomes[label].rule(floor, level, None if among is None else among(outcomes[label]))
                 for label in sets]
        print(f"| {name} | " + " | ".join(f"{n}, {r}, {p:.2f}, {rec:.2f}" for n, r, p, rec in cells) + " |")

    row(f"score >= {TODAY:g} (today)", TODAY, 0.0)
    if trusted is not None:
        row(f"score >= {chosen[0]:g}, confidence >= {trusted:g} (trusted)", chosen[0], trusted)
        row("the same, look-alikes' images left out", chosen[0], trusted, lambda o: o.apart)
    for floor in FLOORS:
        best = choose_rule_at(outcomes["tuning parts"], floor)
        if best is not None:
            row(f"score >= {floor:g}, confidence >= {best:g} (best at this floor)", floor, best)
    if chosen is not None:
        print(f"\ntrade curve at pose.min_score {chosen[0]:g} (the chosen floor):\n\n| rule | {header} |\n|---|" +
              "---|" * len(sets))
        for level in LEVELS:
            row(f"confidence >= {level:g}", chosen[0], level)
        print(f"\nper condition, images with the part only (right of found as bench/accuracy.py counts it):\n\n"
              f"| condition, rule | {header} |\n|---|" + "---|" * len(sets))
        for condition in POSITIVE_CONDITIONS:
            for name, floor, level in ((f"score >= {TODAY:g}", TODAY, 0.0), ("chosen", *chosen)):
                row(f"{condition}, {name}", floor, level, lambda o: o.positive & (o.condition == condition))
    print_reliability(calibration, sets)
    plot_rules(args.confidence_plot, calibration, sets, chosen, trusted)
    print(f"\nwrote {args.confidence_plot}")


def choose_rule_at(outcomes: Outcomes, floor: float, precision: float | None = None, among=None) -> float | None:
    """The level of ``LEVELS`` with the most right poses found at ``floor`` (the more precise
    on a tie) while its precision over the estimates ``among`` (a mask; default all) is at
    least ``precision`` (default: today's rule's) with at least one pose found."""
    if precision is None:
        precision = outcomes.rule(TODAY, 0.0)[2]
    rules = [(level, *outcomes.rule(floor, level, among)[:3]) for level in LEVELS]
    passing = [(right, p, level) for level, found, right, p in rules if p >= precision and found]
    return max(passing)[2] if passing else None


def prior_weights(positive: np.ndarray, prior: float) -> np.ndarray:
    """Weights that make a share ``prior`` of the estimates' images hold the part."""
    share = positive.mean()
    return np.where(positive, prior / share, (1.0 - prior) / (1.0 - share))


def print_reliability(calibration: Calibration, sets: dict) -> None:
    """Mean confidence against the share right and the expected calibration error, at
    several shares of images holding the part, with the prior corrected (pose.prior) and
    left at the fit's mix; then the same per condition where the part is always in view."""
    print("\n| set | part in view in | pose.prior | estimates | mean confidence | right | ECE |\n"
          "|---|---|---|---|---|---|---|")
    for label, records in sets.items():
        x = feature_matrix(records, calibration.features)
        _, correct, positive, _, _ = arrays(records)
        for prior in PRIORS:
            among = positive if prior >= 1.0 else np.ones(len(records), bool)
            weights = prior_weights(positive, prior)[among] if 0.0 < prior < 1.0 else None
            for setting in dict.fromkeys((prior, None)):
                confidence = calibration.probability(x[among], setting, tied(records)[among])
                error, _ = reliability(confidence, correct[among], weights)
                mean = np.average(confidence, weights=weights)
                print(f"| {label} | {prior:.0%} of images | {'fit mix' if setting is None else f'{setting:g}'} | "
                      f"{among.sum()} | {mean:.2f} | {np.average(correct[among], weights=weights):.2f} | "
                      f"{error:.3f} |")
    print("\n| set | condition (part always in view) | images | mean confidence at pose.prior 1 | right |\n"
          "|---|---|---|---|---|")
    for label, records in sets.items():
        o = Outcomes(records, calibration, 1.0)
        for condition in POSITIVE_CONDITIONS:
            mine = o.positive & (o.condition == condition)
            print(f"| {label} | {condition} | {mine.sum()} | {o.confidence[mine].mean():.2f} | "
                  f"{o.correct[mine].mean():.2f} |")


def plot_rules(path: Path, calibration: Calibration, sets: dict, chosen, trusted=None) -> None:
    """Left: precision against recall of the found rules (score alone; the confidence above
    the chosen floor), today's, the chosen and the trusted rule marked. Right: the leave-out
    (else the tuning) parts' reliability at their own mix and where the part is always in view."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.0))
    styles = {"tuning parts": ":", "leave-out parts": "-"}
    floor = TODAY if chosen is None else chosen[0]
    for label, records in sets.items():
        o = Outcomes(records, calibration)
        curve = np.array([o.rule(th, 0.0)[2:] for th in np.linspace(0.3, 1.0, 71)])
        axes[0].plot(curve[:, 1], curve[:, 0], styles[label], color="tab:blue", label=f"{label}: score alone")
        curve = np.array([o.rule(floor, level)[2:] for level in np.linspace(0.0, 0.99, 100)])
        axes[0].plot(curve[:, 1], curve[:, 0], styles[label], color="tab:red",
                     label=f"{label}: score >= {floor:g}, confidence")
        _, _, p, r = o.rule(TODAY, 0.0)
        axes[0].plot([r], [p], "o", color="tab:blue", markersize=6)
        if chosen is not None:
            _, _, p, r = o.rule(*chosen)
            axes[0].plot([r], [p], "*", color="tab:red", markersize=10)
        if trusted is not None:
            _, _, p, r = o.rule(floor, trusted)
            axes[0].plot([r], [p], "D", color="tab:red", markersize=6)
    axes[0].set_xlabel("recall (right poses found / images of the part)")
    axes[0].set_ylabel("precision (right / found)")
    axes[0].set_xlim(0, 0.6)
    axes[0].set_ylim(0, 1.05)
    axes[0].grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="lower left")
    axes[0].set_title(f"o: score >= {TODAY:g}; *: " +
                      ("none chosen" if chosen is None else f"score >= {chosen[0]:g}, confidence >= {chosen[1]:g}") +
                      ("" if trusted is None else f"; diamond: trusted, >= {trusted:g}"), fontsize=8)
    label = "leave-out parts" if "leave-out parts" in sets else "tuning parts"
    records = sets[label]
    x = feature_matrix(records, calibration.features)
    _, correct, positive, _, _ = arrays(records)
    for name, among, setting, style in (("images with and without the part, fit mix", np.ones(len(records), bool),
                                         None, "o-"),
                                        ("part always in view, pose.prior 1", positive, 1.0, "s-"),
                                        ("part always in view, no correction", positive, None, "^:")):
        error, rows = reliability(calibration.probability(x[among], setting, tied(records)[among]), correct[among])
        rows = np.array(rows)
        axes[1].plot(rows[:, 1], rows[:, 2], style, label=f"{name} (ECE {error:.3f})")
    axes[1].plot([0, 1], [0, 1], color="grey", linewidth=1)
    axes[1].set_xlabel("confidence (bin mean)")
    axes[1].set_ylabel("share of poses right")
    axes[1].set_xlim(0, 1)
    axes[1].set_ylim(0, 1.05)
    axes[1].grid(alpha=0.3)
    axes[1].legend(fontsize=7, loc="upper left")
    axes[1].set_title(f"reliability, {label}", fontsize=9)
    save_figure(fig, path, dpi=72)


def tied(records: list[dict]) -> np.ndarray:
    """(N,) whether each estimate was tied with a twin (``Estimate.twin_tie``; records written
    before it was kept hold none)."""
    return np.array([bool(r.get("twin_tie", False)) for r in records], bool)


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


def record(result, owner: str, part: str, condition: str, correct: bool, truth_distance: float) -> dict:
    """What one image's estimate reported, for fitting and checking a confidence on it: the
    features of ``confidence.FEATURES`` and the confidence of the estimator's calibration;
    and, to tell what a wrong pose is, the image, the pose's errors against the image's part
    (on another part's image: where a look-alike lies) and its centre's distance against the
    truth's (``truth_distance``, metres)."""
    estimate = result.estimate
    shares = estimate.shares._asdict() if estimate.shares is not None else {}
    errors = result.errors.to_dict() if result.errors is not None else {}
    return {"owner": owner, "part": part, "condition": condition, "image": result.image, "correct": correct,
            "margin": estimate.symmetry_margin, "twin_tie": estimate.twin_tie, "confidence": float(estimate.confidence),
            **shares,
            **features(estimate), **{k: float(v) for k, v in errors.items()}, "distance": estimate.distance,
            "truth_distance": truth_distance}


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

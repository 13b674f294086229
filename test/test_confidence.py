"""The confidence: its fit, its calibration file, and the shipped calibration."""
import numpy as np
import pytest
import yaml

from brepose_ros.evaluation.metrics import precision_lower_bound, reliability
from brepose_ros.online.confidence import (COIN_TOSS, FEATURES, Calibration, Logistic, features, load_calibration,
                                          shipped_path)
from brepose_ros.online.estimator import Estimate, is_found, not_found_reason
from brepose_ros.online.scoring import Shares
from brepose_ros.params import EstimatorParams

NAMES = ("score", "explained", "error_ratio")


def synthetic(weights, bias, n=20000, seed=0):
    """Raw features with known means and spreads and outcomes drawn from the logistic model."""
    rng = np.random.default_rng(seed)
    mean, scale = np.array([0.6, 0.8, 0.4]), np.array([0.2, 0.1, 0.25])
    x = mean + scale * rng.standard_normal((n, 3))
    z = (x - x.mean(axis=0)) / x.std(axis=0)
    p = 1.0 / (1.0 + np.exp(-(bias + z @ np.asarray(weights))))
    return x, rng.random(n) < p


def test_the_fit_recovers_known_weights():
    weights, bias = [2.0, -1.0, 0.0], -0.5
    x, y = synthetic(weights, bias)
    fitted = Logistic.fit(x, y, l2=1e-6)
    np.testing.assert_allclose(fitted.weights, weights, atol=0.1)
    assert fitted.bias == pytest.approx(bias, abs=0.1)
    # calibrated: among estimates given about 0.7, about 70 % are right
    p = fitted.probability(x)
    band = (p > 0.65) & (p < 0.75)
    assert y[band].mean() == pytest.approx(0.7, abs=0.03)


def test_the_l2_term_keeps_a_perfect_separator_finite():
    x = np.array([[0.1, 0.8, 0.4], [0.2, 0.8, 0.4], [0.8, 0.8, 0.4], [0.9, 0.8, 0.4]])
    fitted = Logistic.fit(x, np.array([False, False, True, True]), l2=0.01)
    assert 0 < fitted.weights[0] < 20 and fitted.weights[1] == 0.0  # a constant feature gets no weight
    assert fitted.probability(x[:1])[0] < 0.5 < fitted.probability(x[3:])[0]


def bench(share, n, seed):
    """Estimates of a bench where a share ``share`` of the images hold the part: features
    drawn apart for images with and without it (the score higher with it), the pose right
    on an image with the part with a probability rising with the score."""
    rng = np.random.default_rng(seed)
    present = rng.random(n) < share
    x = np.where(present[:, None], [0.7, 0.8, 0.3], [0.45, 0.7, 0.5]) + [0.15, 0.1, 0.2] * rng.standard_normal((n, 3))
    right = present & (rng.random(n) < 1.0 / (1.0 + np.exp(-(x[:, 0] - 0.7) / 0.1)))
    return x, right, present


def test_the_prior_moves_the_confidence_to_the_share_of_images_holding_the_part():
    fitted = Calibration.fit(*bench(0.5, 20000, 1), NAMES, l2=1e-6)
    assert fitted.prior == pytest.approx(0.5, abs=0.01)
    x = np.array([[0.6, 0.8, 0.4]])
    rare, fit_mix, often, always = (fitted.probability(x, prior)[0] for prior in (0.1, None, 0.9, 1.0))
    assert 0.0 == fitted.probability(x, 0.0)[0] < rare < fit_mix < often < always
    assert always == pytest.approx(fitted.right.probability(x)[0])
    assert fitted.probability(x, 0.5)[0] == pytest.approx(fit_mix, abs=0.01)
    # checked on a bench where 90 % of the images hold the part: calibrated with the prior
    # said, understated without it
    x, right, _ = bench(0.9, 20000, 2)
    corrected, _ = reliability(fitted.probability(x, 0.9), right)
    uncorrected, _ = reliability(fitted.probability(x), right)
    assert corrected < 0.015 and uncorrected > 0.03
    assert fitted.probability(x, 0.9).mean() == pytest.approx(right.mean(), abs=0.02)
    assert fitted.probability(x).mean() < right.mean() - 0.03


def test_fitting_needs_images_with_and_without_the_part():
    x, right, present = bench(0.5, 200, 3)
    with pytest.raises(ValueError, match="with the part and without it"):
        Calibration.fit(x[present], right[present], present[present], NAMES)


def test_a_missing_feature_counts_as_the_fits_mean_and_a_fit_needs_every_feature():
    """A graph without the part's surface has no shading fit: the confidence counts the
    missing value (nan) as the fit's mean, neither for nor against the pose, where it would
    otherwise be nan; fitting on such estimates is refused, naming the remedy."""
    x, right, present = bench(0.5, 2000, 4)
    fitted = Calibration.fit(x, right, present, NAMES)
    row = np.array([[0.6, np.nan, 0.4]])
    at_mean = np.array([[0.6, fitted.right.mean[1], 0.4]])
    # each model fills in its own mean
    np.testing.assert_allclose(fitted.probability(row), [fitted.present.probability(
        [[0.6, fitted.present.mean[1], 0.4]])[0] * fitted.right.probability(at_mean)[0]])
    assert np.isfinite(fitted.probability(row)).all()
    assert np.isnan(features(estimate(0.8))["shading_fit"]) and features(estimate(0.8, shading_fit=0.9))[
        "shading_fit"] == 0.9
    x[0, 1] = np.nan
    with pytest.raises(ValueError, match="recompile"):
        Calibration.fit(x, right, present, NAMES)


def test_the_expected_calibration_error_measures_the_gap():
    rng = np.random.default_rng(4)
    stated = rng.random(50000)
    error, rows = reliability(stated, rng.random(50000) < stated)
    assert error < 0.01 and len(rows) == 10
    error, _ = reliability(stated, rng.random(50000) < stated * 0.8)  # 20 % overstated
    assert error == pytest.approx(0.1, abs=0.01)
    # weights re-weigh: doubling the weight of the upper half makes its bins count twice
    weights = np.where(stated > 0.5, 2.0, 1.0)
    _, rows = reliability(stated, stated > 0.3, weights)
    assert rows[-1][0] == pytest.approx(2 * rows[0][0], rel=0.1)


def test_the_precision_lower_bound_is_wilsons_and_tightens_with_more_poses():
    assert precision_lower_bound(8, 10) == pytest.approx(0.4902, abs=1e-4)  # the textbook Wilson interval
    assert precision_lower_bound(11, 11) == pytest.approx(11 / (11 + 1.96 ** 2))  # all right: n / (n + z^2)
    assert precision_lower_bound(0, 0) == 0.0
    # the same measured precision supports more the more poses it rests on
    bounds = [precision_lower_bound(19 * n, 20 * n) for n in (1, 4, 16, 64)]
    assert all(a < b < 0.95 for a, b in zip(bounds, bounds[1:]))
    assert bounds[-1] > 0.93
    # a wider interval (z) gives a lower end
    assert precision_lower_bound(19, 20, z=2.58) < precision_lower_bound(19, 20)


def calibration():
    x, right, present = bench(0.5, 500, 5)
    return Calibration.fit(x, right, present, NAMES, provenance={"parts": ["a", "b"], "estimates": 500})


def test_the_file_round_trips(tmp_path):
    model = calibration()
    model.save(tmp_path / "c.yaml", header="a test")
    loaded = Calibration.load(tmp_path / "c.yaml")
    assert loaded.features == NAMES and loaded.provenance == {"parts": ["a", "b"], "estimates": 500}
    np.testing.assert_allclose(loaded.right.weights, model.right.weights, rtol=1e-8)
    assert loaded.prior == pytest.approx(model.prior)
    x = np.array([[0.7, 0.85, 0.3], [0.3, 0.9, 0.8]])
    for prior in (None, 0.2, 1.0):
        np.testing.assert_allclose(loaded.probability(x, prior), model.probability(x, prior), rtol=1e-7)
    assert (tmp_path / "c.yaml").read_text().startswith("# a test\n")


@pytest.mark.parametrize("change, message", [
    (lambda d: d["right"]["weights"].__setitem__(0, d["right"]["weights"][0] + 0.5), "checksum does not match"),
    (lambda d: d["present"].__setitem__("bias", d["present"]["bias"] - 1.0), "checksum does not match"),
    (lambda d: d.__setitem__("prior", 0.9), "checksum does not match"),
    (lambda d: d["provenance"].__setitem__("parts", ["a"]), "checksum does not match"),
    (lambda d: d.pop("prior"), "missing prior"),
    (lambda d: d["present"].pop("scale"), "present: missing scale"),
    (lambda d: d.__setitem__("comment", 1), "unknown comment"),
    (lambda d: d.__setitem__("format", 1), "format 1, this version reads format 2"),
    (lambda d: d["features"].__setitem__(1, "colour"), "unknown feature.*colour"),
    (lambda d: d["right"]["weights"].pop(), "right: 3 means, 3 scales, 2 weights"),
    (lambda d: d["features"].pop(), "present: 3 weights for 2 features"),
    (lambda d: d["right"]["scale"].__setitem__(0, -1.0), "right: scale must be positive"),
    (lambda d: d["right"]["mean"].__setitem__(0, float("nan")), "mean must be finite"),
    (lambda d: d["right"].__setitem__("bias", "high"), "bias must be a finite number"),
    (lambda d: d["present"].__setitem__("weights", 3.0), "weights must be a list"),
    (lambda d: d.__setitem__("prior", 1.0), "prior must be a number strictly between 0 and 1"),
])
def test_a_tampered_or_malformed_file_is_refused_naming_the_problem(tmp_path, change, message):
    path = tmp_path / "c.yaml"
    calibration().save(path)
    data = yaml.safe_load(path.read_text())
    change(data)
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match=f"calibration file {path}: .*{message}"):
        Calibration.load(path)


def test_unreadable_files_are_refused(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        Calibration.load(tmp_path / "none.yaml")
    (tmp_path / "bad.yaml").write_text("weights: [1, \n")
    with pytest.raises(ValueError, match="cannot be read"):
        Calibration.load(tmp_path / "bad.yaml")
    (tmp_path / "list.yaml").write_text("[1, 2]\n")
    with pytest.raises(ValueError, match="must be a mapping"):
        Calibration.load(tmp_path / "list.yaml")


def test_the_shipped_calibration_loads_with_its_provenance():
    shipped = load_calibration("")
    assert shipped == Calibration.load(shipped_path())
    assert {"parts", "estimates", "right", "version", "commit"} <= set(shipped.provenance)
    assert set(shipped.features) <= set(FEATURES) and 0.0 < shipped.prior < 1.0
    assert EstimatorParams().pose.confidence_file == ""


def estimate(score, confirmed=None, explained=None, significance=0.9999, **changes):
    values = dict(found=True, R=np.eye(3), t=np.array([0, 0, 0.5]), score=score, error_ratio=0.3, view_index=0,
                  n_image_segments=40, n_matched=10, n_nearest=8,
                  shares=Shares(score if confirmed is None else confirmed, score if explained is None else explained,
                                significance),
                  size_pixels=200.0, model_length_pixels=1500.0)
    return Estimate(**{**values, **changes})


def test_every_feature_is_read_from_an_estimate():
    values = features(estimate(0.8, symmetry_margin=None))
    assert set(values) == set(FEATURES)
    assert values["twin_margin"] == 1.0 and values["log_insignificance"] == pytest.approx(np.log(1e-4))
    assert features(estimate(0.8, shares=None))["confirmed"] == 0.0  # nothing scored
    assert features(estimate(0.8, shares=Shares(0.8, 0.8, 0.9999, run_on=0.25)))["run_on"] == 0.25


def test_the_shipped_confidence_rises_with_the_score():
    shipped = load_calibration("")
    low, high = shipped.confidence(estimate(0.3)), shipped.confidence(estimate(0.95))
    assert 0.0 <= low < high <= 1.0


def test_a_pose_tied_with_its_twin_is_at_most_a_coin_toss():
    """``twin_tie``: a twin the image does not tell from the pose scores as well (the notched
    plate turned half round, its notch unseen), so which one was reported is chance; the
    fitted models alone rated such poses trusted. Without a tie, ambiguous or not, the fitted
    confidence stands."""
    shipped = load_calibration("")
    clear = dict(confirmed=0.95, explained=0.95, significance=0.999999, symmetry_margin=0.0, ambiguous=True)
    tied, untied = (shipped.confidence(estimate(0.95, **clear, twin_tie=tie), 1.0) for tie in (True, False))
    assert untied > COIN_TOSS and tied == pytest.approx(COIN_TOSS)
    # where the part is rarely in view the coin toss is scaled down like any confidence
    assert shipped.confidence(estimate(0.95, **clear, twin_tie=True), 0.1) < tied
    # the records' path (bench/confidence.py) caps the same rows
    x = np.array([[features(estimate(0.95, **clear))[f] for f in shipped.features]] * 2)
    assert shipped.probability(x, 1.0, [True, False]) == pytest.approx([tied, untied])


def judged(e: Estimate, p=None) -> bool:
    """Whether the estimator would report ``e`` under pose parameters ``p`` (default: the
    defaults), its confidence from the shipped calibration as the estimator computes it."""
    p = p or EstimatorParams().pose
    e.confidence = load_calibration("").confidence(e, p.prior)
    return is_found(e, p)


def test_the_found_rule_reports_by_the_confidence_above_a_floor_on_the_score():
    today = EstimatorParams().with_flat({"pose.min_score": 0.6, "pose.min_confidence": 0.0}).pose
    # a clear pose, found by either rule
    assert judged(estimate(0.9, 0.9, 0.9)) and judged(estimate(0.9, 0.9, 0.9), today)
    # below 0.6 but well confirmed (a partly hidden part): found now, not before
    hidden = estimate(0.58, confirmed=0.7, explained=0.8, significance=0.99999)
    assert judged(hidden) and not judged(hidden, today)
    # a small pose barely confirmed, scoring 0.62 (a chance fit on clutter): found before, not now
    chance = estimate(0.62, confirmed=0.5, explained=0.7, significance=0.9, size_pixels=60.0,
                      model_length_pixels=300.0)
    assert judged(chance, today) and not judged(chance)
    # below the score's floor nothing is found, however confident
    floor = EstimatorParams().pose.min_score
    low = estimate(floor - 0.01, confidence=1.0)
    assert not is_found(low, EstimatorParams().pose) and is_found(estimate(floor, confidence=1.0),
                                                                    EstimatorParams().pose)


def test_pose_prior_moves_an_estimates_confidence_with_how_often_the_part_is_in_view():
    shipped, e = load_calibration(""), estimate(0.58, confirmed=0.6, explained=0.8, significance=0.99)
    never, rare, fit_mix, often, always = (shipped.confidence(e, prior) for prior in (0.0, 0.1, 0.5, 0.9, 1.0))
    assert never == 0.0 < rare < fit_mix < often < always < 1.0
    assert fit_mix == pytest.approx(shipped.confidence(e, shipped.prior))
    # the same estimate, not worth reporting where the part is rarely in view, is where it always is
    params = EstimatorParams().with_flat({"pose.min_confidence": 0.1})
    assert not judged(estimate(0.58, 0.6, 0.8, 0.99), params.with_flat({"pose.prior": 0.1}).pose)
    assert judged(estimate(0.58, 0.6, 0.8, 0.99), params.with_flat({"pose.prior": 1.0}).pose)


def test_a_refused_pose_says_which_rule_refused_it():
    """The reason logs and /diagnostics give: the working range when the pose lies outside
    it (however good its score), else the score and the confidence beside their floors."""
    ranged = EstimatorParams().with_flat({"pose.min_distance": 0.4, "pose.max_distance": 0.6}).pose
    far = estimate(0.9, confidence=0.9, distance=0.9)
    assert not is_found(far, ranged)
    assert not_found_reason(far, ranged) == ("the best pose lies 0.9 m away, outside pose.min_distance 0.4 - "
                                             "pose.max_distance 0.6")
    weak = estimate(0.3, confidence=0.01, distance=0.5)
    assert not is_found(weak, ranged)
    assert not_found_reason(weak, ranged) == (f"score 0.30, pose.min_score {ranged.min_score:g}; confidence 0.01, "
                                              f"pose.min_confidence {ranged.min_confidence:g}")


def test_the_trusted_rule_reaches_its_precision_on_the_estimates_it_is_chosen_among():
    """bench/confidence.py's trusted rule: the confidence level with the most right poses whose
    precision reaches the target; where a look-alike's pose outranks every right one no level
    does, until its images are left out."""
    from bench.confidence import Outcomes, choose_rule_at

    def record(part, score, correct):
        return {"owner": "sharp_bracket", "part": part, "condition": "clean", "score": score, "correct": correct}

    records = ([record("sharp_bracket", 0.9, True)] * 4 + [record("sharp_bracket", 0.7, False)] * 2 +
               [record("rounded_bracket", 0.95, False)] * 2 + [record("base_attachment", 0.6, False)] * 3)
    # the confidence rises from about 0.01 at score 0.7 to 0.99 at 0.9
    calibration = Calibration(("score",), Logistic((0.5,), (0.1,), (0.0,), 20.0),
                              Logistic((0.8,), (0.1,), (5.0,), 0.0), 0.5, {})
    outcomes = Outcomes(records, calibration)
    assert list(outcomes.apart) == [True] * 6 + [False] * 2 + [True] * 3
    assert choose_rule_at(outcomes, 0.55, 0.95) is None
    level = choose_rule_at(outcomes, 0.55, 0.95, outcomes.apart)
    found, right, precision, recall = outcomes.rule(0.55, level, outcomes.apart)
    assert (found, right, precision, recall) == (4, 4, 1.0, 4 / 6)
    assert outcomes.rule(0.55, level)[2] == pytest.approx(4 / 6)  # the look-alikes' poses still pass it


def test_the_bench_pools_records_files_and_writes_them_one_estimate_a_line(tmp_path, capsys):
    """bench/confidence.py --from-records with two files judges their estimates pooled, as one
    file holding both; --records writes the pooled estimates back, one a line."""
    import json
    from pathlib import Path
    from bench.confidence import main

    stored = json.loads((Path(__file__).resolve().parents[1] / "docs/results/confidence_records.json").read_text())
    parts = ["sharp_bracket", "base_attachment"]
    mine = [r for r in stored if r["owner"] in parts and r["part"] in parts]
    files = [tmp_path / "first.json", tmp_path / "second.json", tmp_path / "both.json"]
    for path, records in zip(files, (mine[:50], mine[50:], mine)):
        path.write_text(json.dumps(records))
    common = ["--parts", *parts, "--calibration", str(shipped_path()), "--plot", str(tmp_path / "scores.png"),
              "--confidence-plot", str(tmp_path / "rules.png")]
    assert main(["--from-records", str(files[2]), *common]) == 0
    alone = capsys.readouterr().out
    pooled = tmp_path / "pooled.json"
    assert main(["--from-records", str(files[0]), str(files[1]), "--records", str(pooled), *common]) == 0
    assert capsys.readouterr().out == alone
    assert json.loads(pooled.read_text()) == mine
    assert len(pooled.read_text().splitlines()) == len(mine) + 2


def test_the_bench_judges_a_given_calibration_without_fitting_one(tmp_path, capsys):
    """bench/confidence.py --calibration: the found and trusted rules of the shipped file on
    stored estimates, as choose_rule and choose_rule_at give them; no calibration is written."""
    import json
    from pathlib import Path
    from bench.confidence import Outcomes, choose_rule, choose_rule_at, main

    stored = json.loads((Path(__file__).resolve().parents[1] / "docs/results/confidence_records.json").read_text())
    parts = ["sharp_bracket", "base_attachment"]
    records = tmp_path / "records.json"
    records.write_text(json.dumps([r for r in stored if r["owner"] in parts and r["part"] in parts]))
    plots = [tmp_path / "scores.png", tmp_path / "rules.png"]
    argv = ["--from-records", str(records), "--parts", *parts, "--calibration", str(shipped_path()),
            "--plot", str(plots[0]), "--confidence-plot", str(plots[1])]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    outcomes = Outcomes(json.loads(records.read_text()), load_calibration(""))
    floor, level = choose_rule(outcomes)
    assert f"pose.min_score {floor:g}, pose.min_confidence {level:g}" in printed
    trusted = choose_rule_at(outcomes, floor, 0.95, outcomes.apart)
    assert f"pose.min_confidence {trusted:g}" in printed.split("trusted rule")[1].splitlines()[0]
    assert "confidence fitted on" not in printed and all(p.exists() for p in plots)
    with pytest.raises(SystemExit):
        main(argv + ["--fit", str(tmp_path / "fit.yaml")])
    assert not (tmp_path / "fit.yaml").exists()

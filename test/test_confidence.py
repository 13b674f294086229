"""The confidence: its fit, its calibration file, and the shipped calibration."""
import numpy as np
import pytest
import yaml

from brepose_ros.online.confidence import FEATURES, Calibration, features, load_calibration, shipped_path
from brepose_ros.online.estimator import Estimate
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
    fitted = Calibration.fit(x, y, NAMES, l2=1e-6)
    np.testing.assert_allclose(fitted.weights, weights, atol=0.1)
    assert fitted.bias == pytest.approx(bias, abs=0.1)
    # calibrated: among estimates given about 0.7, about 70 % are right
    p = fitted.probability(x)
    band = (p > 0.65) & (p < 0.75)
    assert y[band].mean() == pytest.approx(0.7, abs=0.03)


def test_the_l2_term_keeps_a_perfect_separator_finite():
    x = np.array([[0.1, 0.8, 0.4], [0.2, 0.8, 0.4], [0.8, 0.8, 0.4], [0.9, 0.8, 0.4]])
    fitted = Calibration.fit(x, np.array([False, False, True, True]), NAMES, l2=0.01)
    assert 0 < fitted.weights[0] < 20 and fitted.weights[1] == 0.0  # a constant feature gets no weight
    assert fitted.probability(x[:1])[0] < 0.5 < fitted.probability(x[3:])[0]


def calibration():
    x, y = synthetic([2.0, -1.0, 0.3], -0.5, n=500)
    return Calibration.fit(x, y, NAMES, provenance={"parts": ["a", "b"], "estimates": 500})


def test_the_file_round_trips(tmp_path):
    model = calibration()
    model.save(tmp_path / "c.yaml", header="a test")
    loaded = Calibration.load(tmp_path / "c.yaml")
    assert loaded.features == NAMES and loaded.provenance == {"parts": ["a", "b"], "estimates": 500}
    np.testing.assert_allclose(loaded.weights, model.weights, rtol=1e-8)
    x = np.array([[0.7, 0.85, 0.3], [0.3, 0.9, 0.8]])
    np.testing.assert_allclose(loaded.probability(x), model.probability(x), rtol=1e-7)
    assert (tmp_path / "c.yaml").read_text().startswith("# a test\n")


@pytest.mark.parametrize("change, message", [
    (lambda d: d["weights"].__setitem__(0, d["weights"][0] + 0.5), "checksum does not match"),
    (lambda d: d["provenance"].__setitem__("parts", ["a"]), "checksum does not match"),
    (lambda d: d.pop("scale"), "missing scale"),
    (lambda d: d.__setitem__("comment", 1), "unknown comment"),
    (lambda d: d.__setitem__("format", 2), "format 2"),
    (lambda d: d["features"].__setitem__(1, "colour"), "unknown feature.*colour"),
    (lambda d: d["weights"].pop(), "2 weights for 3 features"),
    (lambda d: d["scale"].__setitem__(0, -1.0), "scale must be positive"),
    (lambda d: d["mean"].__setitem__(0, float("nan")), "mean must be finite"),
    (lambda d: d.__setitem__("bias", "high"), "bias must be a finite number"),
    (lambda d: d.__setitem__("weights", 3.0), "weights must be a list"),
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
    assert set(shipped.features) <= set(FEATURES)
    assert EstimatorParams().pose.confidence_file == ""


def estimate(score, **changes):
    values = dict(found=True, R=np.eye(3), t=np.array([0, 0, 0.5]), score=score, error_ratio=0.3, view_index=0,
                  n_image_segments=40, n_matched=10, n_nearest=8, shares=Shares(score, score, 0.9999),
                  size_pixels=200.0, model_length_pixels=1500.0)
    return Estimate(**{**values, **changes})


def test_every_feature_is_read_from_an_estimate():
    values = features(estimate(0.8, symmetry_margin=None))
    assert set(values) == set(FEATURES)
    assert values["twin_margin"] == 1.0 and values["log_insignificance"] == pytest.approx(np.log(1e-4))
    assert features(estimate(0.8, shares=None))["confirmed"] == 0.0  # nothing scored


def test_the_shipped_confidence_rises_with_the_score():
    shipped = load_calibration("")
    low, high = shipped.confidence(estimate(0.3)), shipped.confidence(estimate(0.95))
    assert 0.0 <= low < high <= 1.0

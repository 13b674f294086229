"""The confidence of an estimate: the probability that its pose is right, from what the
estimator knows at the final pose.

The score (``scoring``) ranks poses of one image, but it is not a probability across
images: a pose reported at 0.6 was right 43 % of the time on the leave-out parts
(docs/results/confidence.md). Two logistic models on a few numbers the estimate already
has (``FEATURES``: the score, its shares, the error ratio, the twin margin, ...) turn them
into one, ``Calibration.confidence``:

    P(right) = P(the part is in view | x) * P(the pose is right | x, the part is in view)

The first factor depends on how often the part is in view at all (the prior), which a
cell knows and the fitting bench cannot: it was fitted at the bench's mix
(``Calibration.prior``) and is moved to the cell's ``pose.prior`` by Bayes' rule (its
log-odds shifted by the difference of the priors' log-odds). At prior 1 the confidence
is the second factor alone.

The weights are learned, not hand-set (``Logistic.fit``: L2-regularised logistic
regressions on standardised features, scipy's L-BFGS), on estimates whose correctness is
known (bench/confidence.py ``--fit``: the tuning parts' scenes with and without the part),
and shipped with their provenance in ``brepose_ros/confidence.yaml``, which the estimator
loads by default (``pose.confidence_file`` names another). The file carries a checksum of
its numbers: a hand-edited or damaged file is refused, naming what is wrong.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np
import yaml

if TYPE_CHECKING:
    from .estimator import Estimate

#: the calibration file's layout; a file of another format is refused (format 1: one model, no prior)
FORMAT = 2
#: the shipped calibration, inside the package so that every kind of install finds it
SHIPPED = "confidence.yaml"

#: what a confidence may be computed from, each a number the estimate already holds
FEATURES: dict[str, Callable[["Estimate"], float]] = {
    "score": lambda e: e.score,
    "confirmed": lambda e: e.shares.confirmed if e.shares else 0.0,
    "explained": lambda e: e.shares.explained if e.shares else 0.0,
    # log(1 - significance): minus the confirmed evidence over SIGNIFICANT_PIXELS, which the
    # significance itself squashes to 1 for every clear pose
    "log_insignificance": lambda e: math.log(max(1.0 - e.shares.significance, 1e-12)) if e.shares else 0.0,
    "error_ratio": lambda e: e.error_ratio,
    # a part without near symmetries has no twin to be confused with
    "twin_margin": lambda e: 1.0 if e.symmetry_margin is None else e.symmetry_margin,
    "ambiguous": lambda e: float(e.ambiguous),
    "log_size": lambda e: math.log(max(e.size_pixels, 1.0)),
    "log_model_length": lambda e: math.log(max(e.model_length_pixels, 1.0)),
    "log_image_lines": lambda e: math.log1p(e.n_image_segments),
    # the image's edges running on past the model's ends: a factor of the score already, at a
    # hand-set weight (scoring.RUN_ON_WEIGHT); alone it adds to the fit (docs/results/confidence.md)
    "run_on": lambda e: e.shares.run_on if e.shares else 0.0,
    # the region's evidence beside the edges' (online/appearance.py); nan, missing, where the
    # graph holds no surface
    "shading_fit": lambda e: math.nan if e.shading_fit is None else e.shading_fit,
}


#: the most the confidence says, where the part is in view, of a pose tied with a twin
#: (``Estimate.twin_tie``): the image shows neither more than the other and they score alike,
#: so which was reported is a coin toss. The models were fitted on the tuning parts, nearly
#: free of such twins, and rated some of those poses trusted (the notched plate turned half
#: round: 0.59); tied poses were right 7 of the 12 found it held down on the bench's images
#: 0-15, 4 of 44 on images 32-47 (docs/results/symmetry.md)
COIN_TOSS = 0.5


def features(estimate: "Estimate") -> dict[str, float]:
    """Every feature of ``FEATURES`` for one estimate."""
    return {name: float(get(estimate)) for name, get in FEATURES.items()}


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class Logistic:
    """P = 1 / (1 + exp(-(bias + weights . (x - mean) / scale))) over rows of raw features x."""

    mean: tuple[float, ...]
    scale: tuple[float, ...]
    weights: tuple[float, ...]
    bias: float

    def __post_init__(self):
        for name in ("mean", "scale", "weights"):
            values = getattr(self, name)
            if not all(_finite(v) for v in values):
                raise ValueError(f"{name} must be finite numbers, got {list(values)}")
        if len({len(self.mean), len(self.scale), len(self.weights)}) != 1:
            raise ValueError(f"{len(self.mean)} means, {len(self.scale)} scales, {len(self.weights)} weights")
        if not all(s > 0 for s in self.scale):
            raise ValueError(f"scale must be positive, got {list(self.scale)}")
        if not _finite(self.bias):
            raise ValueError(f"bias must be a finite number, got {self.bias!r}")

    def logit(self, x: np.ndarray) -> np.ndarray:
        """The model's log-odds of rows of raw features (N, F); a missing feature (nan: the
        shading fit of a graph without the part's surface) counts as the fit's mean, moving
        the odds neither way."""
        x = np.asarray(x, float)
        x = np.where(np.isnan(x), np.asarray(self.mean), x)
        z = (x - np.asarray(self.mean)) / np.asarray(self.scale)
        return self.bias + z @ np.asarray(self.weights)

    def probability(self, x: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.logit(x)))

    @classmethod
    def fit(cls, x: np.ndarray, y: np.ndarray, l2: float = 0.01) -> "Logistic":
        """Logistic regression of ``y`` (N,) on the raw features ``x`` (N, F), standardised;
        ``l2`` times the squared weights (not the bias) is added to the mean log-loss, so
        that a feature that separates the few training estimates perfectly does not get an
        infinite weight."""
        from scipy.optimize import minimize

        x, y = np.asarray(x, float), np.asarray(y, float)
        if not np.isfinite(x).all():
            raise ValueError("fitting needs every feature of every estimate (a shading fit is missing where the "
                             "aspect graph holds no surface: recompile it)")
        mean, scale = x.mean(axis=0), x.std(axis=0)
        scale[scale < 1e-9] = 1.0  # a constant feature: its weight stays 0 under the L2 term
        z = (x - mean) / scale

        def loss(w):
            logit = w[0] + z @ w[1:]
            # log(1 + exp(-s)) with s = logit for y = 1 and -logit for y = 0, stable both ways
            signed = np.where(y > 0, logit, -logit)
            p = 1.0 / (1.0 + np.exp(-logit))
            value = np.mean(np.logaddexp(0.0, -signed)) + l2 * w[1:] @ w[1:]
            residual = (p - y) / len(y)
            return value, np.concatenate([[residual.sum()], z.T @ residual + 2 * l2 * w[1:]])

        w = minimize(loss, np.zeros(x.shape[1] + 1), jac=True, method="L-BFGS-B").x
        return cls(tuple(map(float, mean)), tuple(map(float, scale)), tuple(map(float, w[1:])), float(w[0]))

    def numbers(self) -> dict:
        return {"mean": list(self.mean), "scale": list(self.scale), "weights": list(self.weights), "bias": self.bias}

    def rounded(self) -> "Logistic":
        """The same model with its numbers as the file keeps them (9 significant digits)."""
        def r(values):
            return tuple(float(f"{v:.9g}") for v in values)

        return Logistic(r(self.mean), r(self.scale), r(self.weights), r([self.bias])[0])

    @classmethod
    def from_dict(cls, data, name: str) -> "Logistic":
        if not isinstance(data, dict):
            raise ValueError(f"{name} must be a mapping")
        expected = {"mean", "scale", "weights", "bias"}
        missing, extra = expected - set(data), set(data) - expected
        if missing or extra:
            raise ValueError(f"{name}: " + ", ".join(([f"missing {', '.join(sorted(missing))}"] if missing else []) +
                                                   ([f"unknown {', '.join(sorted(extra))}"] if extra else [])))
        for key in ("mean", "scale", "weights"):
            if not isinstance(data[key], list):
                raise ValueError(f"{name}: {key} must be a list, got {data[key]!r}")
        try:
            return cls(tuple(data["mean"]), tuple(data["scale"]), tuple(data["weights"]), data["bias"])
        except ValueError as exc:
            raise ValueError(f"{name}: {exc}") from None


def shifted_log_odds(prior: float, fitted_prior: float) -> float:
    """What Bayes' rule adds to the log-odds that the part is in view when it is in view in
    a share ``prior`` of the images instead of the fit's ``fitted_prior`` (inf at prior 1,
    -inf at 0)."""
    if prior >= 1.0:
        return math.inf
    if prior <= 0.0:
        return -math.inf
    return math.log(prior / (1.0 - prior)) - math.log(fitted_prior / (1.0 - fitted_prior))


@dataclass(frozen=True)
class Calibration:
    """The confidence (module doc): ``present``, whether the part is in view, fitted on
    every estimate at the share ``prior`` of images holding the part; ``right``, whether
    the pose is right, fitted on the estimates of images holding it; both over the named
    ``features``; with where and on what they were fitted (``provenance``)."""

    features: tuple[str, ...]
    present: Logistic
    right: Logistic
    prior: float
    provenance: dict

    def __post_init__(self):
        unknown = [f for f in self.features if f not in FEATURES]
        if unknown:
            raise ValueError(f"unknown feature(s) {', '.join(unknown)} (known: {', '.join(FEATURES)})")
        if not self.features:
            raise ValueError("no features")
        for name in ("present", "right"):
            if len(getattr(self, name).weights) != len(self.features):
                raise ValueError(f"{name}: {len(getattr(self, name).weights)} weights for {len(self.features)} "
                                 "features")
        if not (_finite(self.prior) and 0.0 < self.prior < 1.0):
            raise ValueError(f"prior must be a number strictly between 0 and 1, got {self.prior!r}")

    def probability(self, x: np.ndarray, prior: float | None = None,
                    tied: np.ndarray | list[bool] | None = None) -> np.ndarray:
        """The confidence of rows of raw features (N, F) in ``features`` order where a share
        ``prior`` of the images hold the part (None: the fit's own mix); the rows ``tied``
        (N,) with a twin (``Estimate.twin_tie``; None: none) are right at most ``COIN_TOSS``
        of the times the part is in view."""
        shift = 0.0 if prior is None else shifted_log_odds(prior, self.prior)
        with np.errstate(over="ignore"):  # exp(inf) at prior 0 gives the right limit, 0
            present = 1.0 / (1.0 + np.exp(-(self.present.logit(x) + shift)))
        right = self.right.probability(x)
        if tied is not None:
            right = np.where(np.asarray(tied, bool), np.minimum(right, COIN_TOSS), right)
        return present * right

    def confidence(self, estimate: "Estimate", prior: float | None = None) -> float:
        """The probability that ``estimate``'s pose is right, in [0, 1] (``probability``)."""
        values = features(estimate)
        return float(self.probability(np.array([[values[f] for f in self.features]]), prior, [estimate.twin_tie])[0])

    @classmethod
    def fit(cls, x: np.ndarray, correct: np.ndarray, present: np.ndarray, names: tuple[str, ...],
            l2: float = 0.01, provenance: dict | None = None) -> "Calibration":
        """Both models on raw features ``x`` (N, F) named ``names``: ``present`` (N,) whether
        each estimate's image holds the part, ``correct`` (N,) whether its pose is right."""
        x, correct, present = np.asarray(x, float), np.asarray(correct, bool), np.asarray(present, bool)
        if not present.any() or present.all():
            raise ValueError("fitting needs estimates of images with the part and without it")
        return cls(tuple(names), Logistic.fit(x, present, l2), Logistic.fit(x[present], correct[present], l2),
                   float(present.mean()), dict(provenance or {}))

    def numbers(self) -> dict:
        return {"features": list(self.features), "present": self.present.numbers(), "right": self.right.numbers(),
                "prior": self.prior}

    def checksum(self) -> str:
        """sha256 of the numbers and the provenance, as written (rounded to the file's digits)."""
        text = json.dumps({**self.numbers(), "provenance": self.provenance}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()

    def rounded(self) -> "Calibration":
        """The same model with its numbers as the file keeps them (9 significant digits)."""
        return Calibration(self.features, self.present.rounded(), self.right.rounded(), float(f"{self.prior:.9g}"),
                           self.provenance)

    def save(self, path: str | Path, header: str = "") -> None:
        """A YAML file that ``load`` reads back to the same model; ``header`` as its leading comments."""
        model = self.rounded()
        body = {"format": FORMAT, **model.numbers(), "provenance": model.provenance, "checksum": model.checksum()}
        comments = "".join(f"# {line}\n" for line in header.splitlines())
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(comments + yaml.safe_dump(body, sort_keys=False, width=100))

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        """Read a calibration file; ValueError naming the file and the problem if it is
        missing, malformed, or its numbers do not match its checksum."""
        try:
            data = yaml.safe_load(Path(path).read_text())
        except FileNotFoundError:
            raise ValueError(f"calibration file {path} does not exist") from None
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
            raise ValueError(f"calibration file {path} cannot be read: {' '.join(str(exc).split())}") from None
        try:
            return cls.from_dict(data)
        except ValueError as exc:
            raise ValueError(f"calibration file {path}: {exc}") from None

    @classmethod
    def from_dict(cls, data) -> "Calibration":
        if not isinstance(data, dict):
            raise ValueError(f"must be a mapping, got {type(data).__name__}")
        if "format" in data and data["format"] != FORMAT:
            raise ValueError(f"format {data['format']!r}, this version reads format {FORMAT} "
                             "(fit it again: python bench/confidence.py --fit FILE)")
        expected = {"format", "features", "present", "right", "prior", "provenance", "checksum"}
        missing, extra = expected - set(data), set(data) - expected
        if missing or extra:
            raise ValueError(", ".join(([f"missing {', '.join(sorted(missing))}"] if missing else []) +
                                       ([f"unknown {', '.join(sorted(extra))}"] if extra else [])))
        if not isinstance(data["features"], list):
            raise ValueError(f"features must be a list, got {data['features']!r}")
        if not isinstance(data["provenance"], dict):
            raise ValueError("provenance must be a mapping")
        model = cls(tuple(data["features"]), Logistic.from_dict(data["present"], "present"),
                    Logistic.from_dict(data["right"], "right"), data["prior"], data["provenance"])
        if model.checksum() != data["checksum"]:
            raise ValueError("checksum does not match its numbers: edited or damaged after fitting "
                             "(fit it again: python bench/confidence.py --fit FILE)")
        return model


def shipped_path() -> Path:
    return Path(str(resources.files("brepose_ros") / SHIPPED))


@lru_cache(maxsize=8)
def load_calibration(path: str = "") -> Calibration:
    """The calibration of ``pose.confidence_file`` (empty: the shipped one), read once per path."""
    return Calibration.load(path or shipped_path())

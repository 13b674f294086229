"""The confidence of an estimate: the probability that its pose is right, from what the
estimator knows at the final pose.

The score (``scoring``) ranks poses of one image, but it is not a probability across
images: a pose reported at 0.6 was right 43 % of the time on the leave-out parts
(docs/results/confidence.md). A logistic model on a few numbers the estimate already has
(``FEATURES``: the score, its shares, the error ratio, the twin margin, the projected
size, the image's line count) turns them into one: ``Calibration.confidence``.

Its weights are learned, not hand-set (``Calibration.fit``: an L2-regularised logistic
regression on standardised features, scipy's L-BFGS), on estimates whose correctness is
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

#: the calibration file's layout; a file of another format is refused
FORMAT = 1
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
}


def features(estimate: "Estimate") -> dict[str, float]:
    """Every feature of ``FEATURES`` for one estimate."""
    return {name: float(get(estimate)) for name, get in FEATURES.items()}


@dataclass(frozen=True)
class Calibration:
    """A logistic model: confidence = 1 / (1 + exp(-(bias + weights . (x - mean) / scale)))
    over the named ``features`` x, with where and on what it was fitted (``provenance``)."""

    features: tuple[str, ...]
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    weights: tuple[float, ...]
    bias: float
    provenance: dict

    def __post_init__(self):
        unknown = [f for f in self.features if f not in FEATURES]
        if unknown:
            raise ValueError(f"unknown feature(s) {', '.join(unknown)} (known: {', '.join(FEATURES)})")
        if not self.features:
            raise ValueError("no features")
        for name in ("mean", "scale", "weights"):
            values = getattr(self, name)
            if len(values) != len(self.features):
                raise ValueError(f"{len(values)} {name} for {len(self.features)} features")
            if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
                raise ValueError(f"{name} must be finite numbers, got {list(values)}")
        if not all(s > 0 for s in self.scale):
            raise ValueError(f"scale must be positive, got {list(self.scale)}")
        if not (isinstance(self.bias, (int, float)) and math.isfinite(self.bias)):
            raise ValueError(f"bias must be a finite number, got {self.bias!r}")

    def logit(self, x: np.ndarray) -> np.ndarray:
        """The model's log-odds of rows of raw features (N, F) in ``features`` order."""
        z = (np.asarray(x, float) - np.asarray(self.mean)) / np.asarray(self.scale)
        return self.bias + z @ np.asarray(self.weights)

    def probability(self, x: np.ndarray) -> np.ndarray:
        return 1.0 / (1.0 + np.exp(-self.logit(x)))

    def confidence(self, estimate: "Estimate") -> float:
        """The probability that ``estimate``'s pose is right, in [0, 1]."""
        values = features(estimate)
        return float(self.probability(np.array([[values[f] for f in self.features]]))[0])

    @classmethod
    def fit(cls, x: np.ndarray, correct: np.ndarray, names: tuple[str, ...], l2: float = 0.01,
            provenance: dict | None = None) -> "Calibration":
        """Logistic regression of ``correct`` (N,) on the raw features ``x`` (N, F) named
        ``names``, standardised; ``l2`` times the squared weights (not the bias) is added to
        the mean log-loss, so that a feature that separates the few training estimates
        perfectly does not get an infinite weight."""
        from scipy.optimize import minimize

        x, y = np.asarray(x, float), np.asarray(correct, float)
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
        return cls(tuple(names), tuple(map(float, mean)), tuple(map(float, scale)), tuple(map(float, w[1:])),
                   float(w[0]), dict(provenance or {}))

    def numbers(self) -> dict:
        return {"features": list(self.features), "mean": list(self.mean), "scale": list(self.scale),
                "weights": list(self.weights), "bias": self.bias}

    def checksum(self) -> str:
        """sha256 of the numbers and the provenance, as written (rounded to the file's digits)."""
        text = json.dumps({**self.numbers(), "provenance": self.provenance}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()

    def rounded(self) -> "Calibration":
        """The same model with its numbers as the file keeps them (9 significant digits)."""
        def r(values):
            return tuple(float(f"{v:.9g}") for v in values)

        return Calibration(self.features, r(self.mean), r(self.scale), r(self.weights), r([self.bias])[0],
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
        expected = {"format", "features", "mean", "scale", "weights", "bias", "provenance", "checksum"}
        missing, extra = expected - set(data), set(data) - expected
        if missing or extra:
            raise ValueError(", ".join(([f"missing {', '.join(sorted(missing))}"] if missing else []) +
                                       ([f"unknown {', '.join(sorted(extra))}"] if extra else [])))
        if data["format"] != FORMAT:
            raise ValueError(f"format {data['format']!r}, this version reads format {FORMAT}")
        for name in ("features", "mean", "scale", "weights"):
            if not isinstance(data[name], list):
                raise ValueError(f"{name} must be a list, got {data[name]!r}")
        if not isinstance(data["provenance"], dict):
            raise ValueError("provenance must be a mapping")
        model = cls(tuple(data["features"]), tuple(data["mean"]), tuple(data["scale"]), tuple(data["weights"]),
                    data["bias"], data["provenance"])
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

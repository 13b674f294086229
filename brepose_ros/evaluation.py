"""Metrics of ../shared/CONVENTIONS.md, shared by brepose-eval, the benchmarks and the tests."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from .geometry import rotation_angle_deg


def viewing_direction(R: np.ndarray) -> np.ndarray:
    """The camera's optical axis expressed in the model frame."""
    return np.asarray(R).T @ np.array([0.0, 0.0, 1.0])


def pose_error_rate(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Seed paper eq. 2 as CONVENTIONS.md: (1 - cos angle between viewing directions) / 2."""
    e, g = viewing_direction(R_est), viewing_direction(R_gt)
    return float((1.0 - e @ g / (np.linalg.norm(e) * np.linalg.norm(g))) / 2.0)


def translation_error_mm(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    return float(np.linalg.norm(np.asarray(t_est) - np.asarray(t_gt)) * 1000.0)


class ModelPoints:
    """Surface points of a part (metres) for ADD / ADD-S, and its true diameter."""

    def __init__(self, points: np.ndarray):
        self.points = np.asarray(points, dtype=float)
        hull = self.points[ConvexHull(self.points).vertices]
        self.diameter = float(np.max(np.linalg.norm(hull[:, None] - hull[None, :], axis=2)))

    @classmethod
    def from_mesh(cls, vertices: np.ndarray, triangles: np.ndarray, count: int = 3000, seed: int = 0):
        """Area-weighted samples of a triangle mesh (deterministic), plus its vertices."""
        rng = np.random.default_rng(seed)
        tri = vertices[triangles]
        area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        pick = rng.choice(len(tri), size=count, p=area / area.sum())
        u, v = rng.random(count), rng.random(count)
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        chosen = tri[pick]
        samples = chosen[:, 0] + u[:, None] * (chosen[:, 1] - chosen[:, 0]) + v[:, None] * (chosen[:, 2] - chosen[:, 0])
        return cls(np.concatenate([vertices, samples]))

    def add(self, R_est, t_est, R_gt, t_gt) -> float:
        """Mean distance of corresponding points, as a fraction of the diameter."""
        a = self.points @ np.asarray(R_est).T + t_est
        b = self.points @ np.asarray(R_gt).T + t_gt
        return float(np.mean(np.linalg.norm(a - b, axis=1)) / self.diameter)

    def add_s(self, R_est, t_est, R_gt, t_gt) -> float:
        """Mean distance to the nearest transformed point (symmetry-aware), fraction of diameter."""
        a = self.points @ np.asarray(R_est).T + t_est
        b = self.points @ np.asarray(R_gt).T + t_gt
        return float(np.mean(cKDTree(b).query(a)[0]) / self.diameter)


@dataclass
class PoseErrors:
    """All errors of one estimated pose against its ground truth."""

    rotation_deg: float
    translation_mm: float
    error_rate: float
    add: float
    add_s: float
    success: bool  # rotation < 5 deg and translation < 5 % of the diameter

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def pose_errors(R_est, t_est, R_gt, t_gt, model: ModelPoints) -> PoseErrors:
    rot = rotation_angle_deg(R_est, R_gt)
    trans = translation_error_mm(t_est, t_gt)
    return PoseErrors(rot, trans, pose_error_rate(R_est, R_gt),
                      model.add(R_est, t_est, R_gt, t_gt), model.add_s(R_est, t_est, R_gt, t_gt),
                      bool(rot < 5.0 and trans < 0.05 * model.diameter * 1000.0))


def summarise(errors: list[PoseErrors | None]) -> dict:
    """Rates and medians over a scene; None marks an image where nothing was found."""
    n = len(errors)
    found = [e for e in errors if e is not None]

    def rate(cond):
        return sum(1 for e in found if cond(e)) / n if n else 0.0

    def median(name):
        return float(np.median([getattr(e, name) for e in found])) if found else float("nan")

    return {
        "images": n,
        "found": len(found) / n if n else 0.0,
        "success": rate(lambda e: e.success),
        "er_below_0.01": rate(lambda e: e.error_rate < 0.01),
        "add_s_below_0.1": rate(lambda e: e.add_s < 0.1),
        "add_below_0.1": rate(lambda e: e.add < 0.1),
        "median_rotation_deg": median("rotation_deg"),
        "median_translation_mm": median("translation_mm"),
        "median_error_rate": median("error_rate"),
        "median_add_s": median("add_s"),
    }


def write_predictions(path: str | Path, predictions: list[dict]) -> None:
    """Predictions JSON of CONVENTIONS.md: image, R (9), t (3), score, error_ratio."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(predictions, indent=1) + "\n")


def prediction_entry(image: str, estimate) -> dict:
    found = estimate.found
    return {"image": image,
            "R": np.asarray(estimate.R).ravel().tolist() if found else None,
            "t": np.asarray(estimate.t).ravel().tolist() if found else None,
            "score": float(estimate.score), "error_ratio": float(estimate.error_ratio)}

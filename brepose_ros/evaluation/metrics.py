"""Metrics of ../shared/CONVENTIONS.md, shared by brepose-eval, the benchmarks and the tests."""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import ConvexHull, cKDTree

from ..aspect_graph import AspectGraph
from ..geometry import direction_to, quaternion_from_matrix, rotation_about, rotation_angle_deg
from ..viewsphere import nearest_views
from .figures import pyplot, save_figure


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
    #: the errors against the truth turned by the part's exact symmetries, the nearest of those
    #: equivalent poses (``symmetric_truth``); the plain ones for a part without symmetry
    rotation_sym_deg: float
    translation_sym_mm: float
    success_sym: bool

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def pose_errors(R_est, t_est, R_gt, t_gt, model: ModelPoints, graph: AspectGraph | None = None) -> PoseErrors:
    """CONVENTIONS.md's errors, and with the part's ``graph`` the symmetry-aware ones."""
    rot = rotation_angle_deg(R_est, R_gt)
    trans = translation_error_mm(t_est, t_gt)
    R_sym, t_sym = symmetric_truth(R_est, R_gt, t_gt, graph) if graph is not None else (R_gt, t_gt)
    rot_sym, trans_sym = rotation_angle_deg(R_est, R_sym), translation_error_mm(t_est, t_sym)
    bound_mm = 0.05 * model.diameter * 1000.0
    return PoseErrors(rot, trans, pose_error_rate(R_est, R_gt),
                      model.add(R_est, t_est, R_gt, t_gt), model.add_s(R_est, t_est, R_gt, t_gt),
                      bool(rot < 5.0 and trans < bound_mm), rot_sym, trans_sym,
                      bool(rot_sym < 5.0 and trans_sym < bound_mm))


def symmetric_truth(R_est, R_gt, t_gt, graph: AspectGraph) -> tuple[np.ndarray, np.ndarray]:
    """Of the poses equivalent to the truth under the part's exact symmetries (the graph's:
    discrete ones and turns about continuous axes), the one nearest ``R_est`` in rotation."""
    R_est = np.asarray(R_est, dtype=float)
    R, t = graph.symmetric_poses(np.asarray(R_gt, dtype=float), np.asarray(t_gt, dtype=float),
                                 graph.exact_symmetries)
    R, t = np.concatenate([[R_gt], R]), np.concatenate([[t_gt], t])
    for point, axis in graph.symmetry_axes[graph.exact_axes][:1]:
        # the turn about the axis that brings each pose nearest R_est: the twist about the
        # axis of the rotation between them (swing-twist decomposition of its quaternion)
        for k in range(len(R)):
            x, y, z, w = quaternion_from_matrix(R[k].T @ R_est)
            turn = rotation_about(axis, 2.0 * np.arctan2(np.array([x, y, z]) @ axis, w))
            t[k] = t[k] + R[k] @ (point - turn @ point)
            R[k] = R[k] @ turn
    best = int(np.argmin([rotation_angle_deg(R_est, R_k) for R_k in R]))
    return R[best], t[best]


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
        "success_sym": rate(lambda e: e.success_sym),
        "er_below_0.01": rate(lambda e: e.error_rate < 0.01),
        "add_s_below_0.1": rate(lambda e: e.add_s < 0.1),
        "add_below_0.1": rate(lambda e: e.add < 0.1),
        "median_rotation_deg": median("rotation_deg"),
        "median_translation_mm": median("translation_mm"),
        "median_error_rate": median("error_rate"),
        "median_add_s": median("add_s"),
        "mean_error_rate": mean_error_rate(errors),
    }


#: the error rate counted for an image where nothing was found: the mean ``er`` of a
#: viewing direction drawn at random, (1 - E[cos]) / 2 with E[cos] = 0 over the sphere
NOT_FOUND_ERROR_RATE = 0.5


def mean_error_rate(errors: list[PoseErrors | None]) -> float:
    """Mean ``er`` over a scene (the seed paper's Fig. 7-10), ``NOT_FOUND_ERROR_RATE`` where
    nothing was found: the paper always answers, so a missed part counts as a guess."""
    rates = [NOT_FOUND_ERROR_RATE if e is None else e.error_rate for e in errors]
    return float(np.mean(rates)) if rates else float("nan")


def write_predictions(path: str | Path, predictions: list[dict]) -> None:
    """Predictions JSON of CONVENTIONS.md: image, R (9), t (3), score, error_ratio, and
    the confidence (the probability that the pose is right, ``online/confidence.py``)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(predictions, indent=1) + "\n")


def prediction_entry(image: str, estimate) -> dict:
    """One entry of the predictions JSON; for a part with near symmetries also the pose's
    ``symmetry_margin`` over its twins, whether the image left it ``ambiguous`` and whether a
    twin ties with it (``twin_tie``); where a time budget left steps out, which (``skipped``);
    where the aspect graph holds the part's surface, the pose's ``shading_fit``."""
    found = estimate.found
    entry = {"image": image,
             "R": np.asarray(estimate.R).ravel().tolist() if found else None,
             "t": np.asarray(estimate.t).ravel().tolist() if found else None,
             "score": float(estimate.score), "error_ratio": float(estimate.error_ratio),
             "confidence": float(estimate.confidence)}
    if estimate.symmetry_margin is not None:
        entry.update(symmetry_margin=float(estimate.symmetry_margin), ambiguous=bool(estimate.ambiguous),
                     twin_tie=bool(estimate.twin_tie))
    if estimate.skipped:
        entry["skipped"] = list(estimate.skipped)
    if estimate.shading_fit is not None:
        entry["shading_fit"] = float(estimate.shading_fit)
    return entry


@dataclass
class ImageResult:
    """One image of an evaluated scene."""

    image: str
    estimate: object  # estimator.Estimate
    errors: PoseErrors | None  # None when nothing was found
    view_rank: int  # rank of the final pose's view among the views nearest the truth (0 = nearest)
    matched_view_rank: int  # the same for the view the bipartite matching chose


def evaluate_scene(scene, estimator, model: ModelPoints, on_image=None, paper_only: bool = False) -> list[ImageResult]:
    """Run ``estimator`` over a loaded scene (``scene_folder.load_scene``) and measure every
    image; ``paper_only``: by the seed paper's method alone (``Estimator.estimate``)."""
    graph = estimator.graph
    results = []
    for entry in scene.entries:
        image = cv2.imread(str(entry.path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"cannot read image {entry.path}")
        estimate = estimator.estimate(image, scene.camera, paper_only=paper_only)
        errors = pose_errors(estimate.R, estimate.t, entry.R, entry.t, model, graph) if estimate.found else None
        direction = direction_to(graph.model_center, entry.R, entry.t)
        order = list(nearest_views(graph.view_directions, direction, k=min(graph.n_views, 50)))

        def rank(view):
            return order.index(view) if view in order else len(order)

        results.append(ImageResult(entry.image, estimate, errors, rank(estimate.view_index),
                                   rank(estimate.matched_view)))
        if on_image is not None:
            on_image(image, results[-1])
    return results


def scene_summary(results: list[ImageResult]) -> dict:
    """``summarise`` plus the view-ranking rate and time per image."""
    summary = summarise([r.errors for r in results])
    n = max(len(results), 1)
    summary["view_among_3_nearest"] = sum(r.view_rank < 3 for r in results) / n
    summary["matched_view_among_3_nearest"] = sum(r.matched_view_rank < 3 for r in results) / n
    summary["median_time_ms"] = float(np.median([r.estimate.timings.get("total", 0.0) for r in results]) * 1000)
    return summary


def plot_evaluation(results: list[ImageResult], path: str | Path, diameter_m: float, title: str = "") -> None:
    """Cumulative rotation / translation error curves and score against correctness."""
    plt = pyplot()

    rot = np.sort([r.errors.rotation_deg for r in results if r.errors])
    trans = np.sort([r.errors.translation_mm / (10.0 * diameter_m) for r in results if r.errors])
    n = max(len(results), 1)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, values, label, limit in ((axes[0], rot, "rotation error (deg)", 20),
                                     (axes[1], trans, "translation error (% of diameter)", 20)):
        ax.step(np.concatenate([[0], values]), np.arange(len(values) + 1) / n, where="post")
        ax.set_xlabel(label)
        ax.set_ylabel("share of images")
        ax.set_ylim(0, 1)
        ax.set_xlim(0, limit)
        ax.grid(alpha=0.3)
    scores = np.array([r.estimate.score for r in results])
    correct = np.array([bool(r.errors and r.errors.success) for r in results])
    axes[2].scatter(np.arange(n)[correct], scores[correct], c="tab:green", label="correct", s=14)
    axes[2].scatter(np.arange(n)[~correct], scores[~correct], c="tab:red", label="wrong / not found", s=14)
    axes[2].set_xlabel("image")
    axes[2].set_ylabel("score")
    axes[2].set_ylim(0, 1)
    axes[2].legend(loc="lower right")
    fig.suptitle(title)
    save_figure(fig, path, dpi=90)


def percent(count: int, total: int) -> str:
    """``count`` as a whole percentage of ``total``, halves rounded up: '38 %' for 3 of 8."""
    return f"{int(100 * count / total + 0.5) if total else 0} %"


def found_correct(errors: list[PoseErrors | None]) -> str:
    """The headline of a scene for people: '7 of 8 found, 6 correct (75 %)'; correct is
    CONVENTIONS.md's success, its share of all images."""
    found = sum(e is not None for e in errors)
    correct = sum(e is not None and e.success for e in errors)
    return f"{found} of {len(errors)} found, {correct} correct ({percent(correct, len(errors))})"


#: keys of ``summarise`` / ``scene_summary`` that are shares of all images
RATE_KEYS = ("found", "success", "er_below_0.01", "add_s_below_0.1", "add_below_0.1", "view_among_3_nearest",
             "matched_view_among_3_nearest")


def format_summary(summary: dict) -> str:
    """One line per metric; shares of the images as counts and percentages ('6 of 8 (75 %)')."""
    n = summary["images"]

    def value(key, v):
        if key in RATE_KEYS:
            count = round(v * n)
            return f"{count} of {n} ({percent(count, n)})"
        return f"{v:.3f}" if isinstance(v, float) else f"{v}"
    return "\n".join(f"  {k:28s} {value(k, v)}" for k, v in summary.items())


def precision_recall(scores, correct, n_positive: int, thresholds) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Precision, recall and detection count of ``found = score >= threshold`` per threshold.

    ``scores``/``correct`` have one entry per image (``correct``: found the part at the right
    pose; an image without the part is never correct); ``n_positive`` images hold the part.
    A threshold with no detection has precision 1 (nothing reported, nothing wrong)."""
    scores, correct = np.asarray(scores, dtype=float), np.asarray(correct, dtype=bool)
    found = scores[None, :] >= np.asarray(thresholds, dtype=float)[:, None]
    detections = found.sum(axis=1)
    right = (found & correct[None, :]).sum(axis=1)
    precision = np.where(detections > 0, right / np.maximum(detections, 1), 1.0)
    return precision, right / max(n_positive, 1), detections


def reliability(probability, correct, weights=None, bins: int = 10) -> tuple[float, list[tuple[float, float, float]]]:
    """How far stated probabilities are from the share right: the expected calibration
    error (the weighted mean, over ``bins`` equal-width bins of ``probability``, of
    |mean probability - share right|) and per non-empty bin (weight, mean probability,
    share right). ``weights`` (default 1 each) re-weigh estimates, e.g. to another share of
    images holding the part than the bench's."""
    probability, correct = np.asarray(probability, float), np.asarray(correct, bool)
    weights = np.ones(len(probability)) if weights is None else np.asarray(weights, float)
    index = np.clip((probability * bins).astype(int), 0, bins - 1)
    rows, error = [], 0.0
    for b in range(bins):
        w = weights[index == b]
        if w.sum() <= 0:
            continue
        stated, right = np.average(probability[index == b], weights=w), np.average(correct[index == b], weights=w)
        rows.append((float(w.sum()), float(stated), float(right)))
        error += w.sum() * abs(stated - right)
    return float(error / max(weights.sum(), 1e-12)), rows


def precision_lower_bound(right: int, found: int, z: float = 1.96) -> float:
    """The Wilson score interval's lower end for a precision of ``right`` of ``found`` (``z``
    1.96: the two-sided 95 % interval), the precision the measurement supports, since with a
    handful of found poses the measured share is a loose estimate (11 of 11 right: 0.74).
    0 when nothing is found."""
    if found <= 0:
        return 0.0
    share, spread = right / found, z * z / found
    centre = share + spread / 2
    return float((centre - z * np.sqrt(share * (1 - share) / found + spread / (4 * found))) / (1 + spread))


def calibrate_min_score(scores, correct, target_precision: float = 0.95) -> float | None:
    """The lowest threshold on the score whose detections are right at least
    ``target_precision`` of the time: the ``pose.min_score`` that keeps the reported poses
    trustworthy with the most of them found. Thresholds are the measured scores themselves;
    None when no threshold reaches the precision."""
    candidates = np.unique(np.asarray(scores, dtype=float))
    precision, _, _ = precision_recall(scores, correct, 1, candidates)
    passing = candidates[precision >= target_precision]
    return float(passing[0]) if len(passing) else None

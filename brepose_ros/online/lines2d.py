"""2D line geometry shared by the matcher, the refinement and the scoring: segments are
arrays (N, 2, 2) of end points, in pixels or normalised coordinates alike."""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from .kernels import nearest_lines_kernel


def line_equations(segments: np.ndarray) -> np.ndarray:
    """(K, 3) lines a x + b y + c = 0 with (a, b) a unit normal."""
    start = segments[:, 0]
    dx, dy = segments[:, 1, 0] - start[:, 0], segments[:, 1, 1] - start[:, 1]
    length = np.maximum(np.sqrt(dx * dx + dy * dy), 1e-12)
    lines = np.empty((len(segments), 3))
    lines[:, 0], lines[:, 1] = -dy / length, dx / length
    lines[:, 2] = -(lines[:, 0] * start[:, 0] + lines[:, 1] * start[:, 1])
    return lines


#: ``nearest_lines``' default angle: a pose a little off turns its projected edges by a few degrees
NEAREST_MAX_ANGLE_DEG = 10.0


def nearest_lines(model_2d: np.ndarray, image_2d: np.ndarray, tolerance: float,
                  max_angle_deg: float = NEAREST_MAX_ANGLE_DEG) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices (model, image) pairing each model segment with its best image segment, and
    the distance of each pair (largest distance of the image end points to the model line).

    A model segment keeps the image segment whose end points lie closest to the model's
    line, provided that is within ``tolerance``, the directions agree within
    ``max_angle_deg`` and the two overlap along the line. A compiled loop
    (``kernels.nearest_lines_kernel``, GIL released): it runs hundreds of times per image,
    and as dense (model x image) numpy matrices it was a large share of the refinement.
    """
    if len(model_2d) == 0 or len(image_2d) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    best, best_cost = np.empty(len(model_2d), np.int64), np.empty(len(model_2d))
    nearest_lines_kernel(np.ascontiguousarray(model_2d, dtype=float), np.ascontiguousarray(image_2d, dtype=float),
                         float(tolerance), cos_deg(max_angle_deg), best, best_cost)
    keep = best >= 0
    return np.nonzero(keep)[0], best[keep], best_cost[keep]


@lru_cache(maxsize=8)
def cos_deg(angle_deg: float) -> float:
    """Cosine of a fixed angle, kept: ``nearest_lines`` runs thousands of times per image."""
    return float(np.cos(np.radians(angle_deg)))


def point_segment_distance(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distances of points (..., 2) to segments (..., 2, 2), broadcast against each other
    (x and y kept apart: numpy's overhead on a trailing axis of 2 cost more than the
    arithmetic)."""
    ax, ay = segments[..., 0, 0], segments[..., 0, 1]
    dx, dy = segments[..., 1, 0] - ax, segments[..., 1, 1] - ay
    dd = np.maximum(dx * dx + dy * dy, 1e-18)
    px, py = points[..., 0], points[..., 1]
    u = np.clip(((px - ax) * dx + (py - ay) * dy) / dd, 0.0, 1.0)
    ex, ey = px - (ax + u * dx), py - (ay + u * dy)
    return np.sqrt(ex * ex + ey * ey)


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Corners (K, 2) of the convex hull of points (..., 2)."""
    return cv2.convexHull(np.asarray(points, np.float32).reshape(-1, 2)).reshape(-1, 2).astype(np.float64)


def samples_along(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``counts[i]`` evenly spaced samples on segment i: each sample's segment and its
    fraction along it (the centres of ``counts[i]`` equal pieces)."""
    segment = np.repeat(np.arange(len(counts)), counts)
    offsets = np.arange(len(segment)) - np.repeat(np.cumsum(counts) - counts, counts)
    return segment, (offsets + 0.5) / counts[segment]

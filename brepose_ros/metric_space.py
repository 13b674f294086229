"""The seed paper's metric space (section 3): segment sets normalised for translation and scale.

A segment set is an array (N, 2, 2) of end points. An image region's set and every view's
set are normalised the same way, so that the matcher compares shapes, not positions or
sizes. The matcher uses ``outline_normalisation`` (centroid and square root of the area of
the end points' convex hull): the outline of a part is what an image shows most reliably.
The paper's length-weighted ``normalisation_of`` remains as its fallback for a degenerate
outline and as the frame the graph file stores view coordinates in.

The paper describes a normalised segment by its tetrad (length l, angle of the midpoint
alpha, angle of the perpendicular from the origin to its line theta, length of that
perpendicular r). The matcher uses the same quantities in continuous form
(``matching.describe``: length, midpoint, orientation, foot of the perpendicular), which
under an in-plane rotation turn with the image while lengths and distances from the
origin stay: the matcher relies on that to search the rotation explicitly.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Normalisation:
    """``normalised = (points - center) / scale``."""

    center: np.ndarray  # (2,)
    scale: float

    def apply(self, segments: np.ndarray) -> np.ndarray:
        return (np.asarray(segments, dtype=float) - self.center) / self.scale


def segment_lengths(segments: np.ndarray) -> np.ndarray:
    segments = np.asarray(segments, dtype=float)
    return np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)


def normalisation_of(segments: np.ndarray) -> Normalisation:
    """Length-weighted centroid and RMS radius of a segment set: every point of every
    segment counts once, so for a segment with midpoint m and length l the squared radius
    is |m - c|^2 + l^2 / 12, and short noisy segments weigh little."""
    segments = np.asarray(segments, dtype=float)
    if len(segments) == 0:
        raise ValueError("cannot normalise an empty segment set")
    lengths = segment_lengths(segments)
    total = lengths.sum()
    if total <= 0:
        raise ValueError("cannot normalise segments of zero total length")
    mid = segments.mean(axis=1)
    center = (lengths[:, None] * mid).sum(axis=0) / total
    spread = (lengths * (np.sum((mid - center) ** 2, axis=1) + lengths**2 / 12.0)).sum() / total
    scale = float(np.sqrt(spread))
    if scale <= 0:
        raise ValueError("cannot normalise segments that all sit on one point")
    return Normalisation(center=center, scale=scale)


def outline_normalisation(segments: np.ndarray) -> Normalisation:
    """Centroid and square root of the area of the convex hull of all end points.

    The outline of a part is what an image shows most reliably (part against background),
    while inner edges come and go with lighting; so this normalisation agrees between a
    view and an image that misses some inner edges, where the length-weighted one drifts.
    Points on one line have no area and take the length-weighted normalisation.
    """
    pts = np.asarray(segments, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 3:
        raise ValueError("cannot normalise fewer than two segments")
    hull = cv2.convexHull(pts.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    x, y = hull[:, 0], hull[:, 1]
    xn, yn = np.roll(x, -1), np.roll(y, -1)
    cross = x * yn - xn * y
    area = cross.sum() / 2.0
    if abs(area) < 1e-12 * max(np.ptp(pts), 1e-12) ** 2:
        return normalisation_of(segments)
    center = np.array([((x + xn) * cross).sum(), ((y + yn) * cross).sum()]) / (6.0 * area)
    return Normalisation(center=center, scale=float(np.sqrt(abs(area))))

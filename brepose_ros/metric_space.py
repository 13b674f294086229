"""The seed paper's metric space (section 3): normalised line segments and their tetrads.

A segment set is an array (N, 2, 2) of end points. Both the image's and every view's set
are normalised the same way, so that the matcher compares shapes, not positions or sizes:

* translation: the length-weighted centroid of the segments (every point of every segment
  counts once), and
* scale: the root-mean-square distance of those points from the centroid; for a segment
  with midpoint m and length l this is exactly |m - c|^2 + l^2 / 12, so short noisy
  segments weigh little.

The tetrad of a segment (length l, angle of midpoint alpha, angle of the perpendicular from
the origin to its line theta, length of that perpendicular r) determines it uniquely. Under
an in-plane rotation by phi, alpha and theta both shift by phi while l, r and |m| do not:
the matcher relies on that to search the rotation explicitly (``matching``).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

TETRAD_FIELDS = ("length", "alpha", "theta", "r")


@dataclass(frozen=True)
class Normalisation:
    """``normalised = (points - center) / scale``; undo with ``points = normalised * scale + center``."""

    center: np.ndarray  # (2,)
    scale: float

    def apply(self, segments: np.ndarray) -> np.ndarray:
        return (np.asarray(segments, dtype=float) - self.center) / self.scale

    def undo(self, segments: np.ndarray) -> np.ndarray:
        return np.asarray(segments, dtype=float) * self.scale + self.center


def segment_lengths(segments: np.ndarray) -> np.ndarray:
    segments = np.asarray(segments, dtype=float)
    return np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)


def normalisation_of(segments: np.ndarray, weights: np.ndarray | None = None) -> Normalisation:
    """Length-weighted centroid and RMS radius of a segment set (see module docstring).

    ``weights`` (per segment, default 1) let a caller down-weight segments it trusts less.
    """
    segments = np.asarray(segments, dtype=float)
    if len(segments) == 0:
        raise ValueError("cannot normalise an empty segment set")
    lengths = segment_lengths(segments)
    w = lengths * (1.0 if weights is None else np.asarray(weights, dtype=float))
    total = w.sum()
    if total <= 0:
        raise ValueError("cannot normalise segments of zero total length")
    mid = segments.mean(axis=1)
    center = (w[:, None] * mid).sum(axis=0) / total
    spread = (w * (np.sum((mid - center) ** 2, axis=1) + lengths**2 / 12.0)).sum() / total
    scale = float(np.sqrt(spread))
    if scale <= 0:
        raise ValueError("cannot normalise segments that all sit on one point")
    return Normalisation(center=center, scale=scale)


def tetrads(segments: np.ndarray) -> np.ndarray:
    """(N, 4) array of (length, alpha, theta, r) of normalised segments (N, 2, 2).

    theta is the direction of the perpendicular dropped from the origin onto the segment's
    line, r >= 0 its length. For a line through the origin (r = 0) theta is the normal
    direction with a non-negative y component, so that it is well defined.
    """
    segments = np.asarray(segments, dtype=float)
    a, b = segments[:, 0], segments[:, 1]
    d = b - a
    length = np.linalg.norm(d, axis=1)
    mid = (a + b) / 2.0
    alpha = np.arctan2(mid[:, 1], mid[:, 0])
    normal = np.stack([-d[:, 1], d[:, 0]], axis=1) / np.maximum(length, 1e-12)[:, None]
    r = np.sum(mid * normal, axis=1)
    flip = (r < 0) | ((r == 0) & (normal[:, 1] < 0))
    normal[flip] *= -1.0
    r = np.abs(r)
    theta = np.arctan2(normal[:, 1], normal[:, 0])
    return np.stack([length, alpha, theta, r], axis=1)


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles mapped to [-pi, pi): angles compare on the circle, not as raw numbers."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


def outline_normalisation(segments: np.ndarray) -> Normalisation:
    """Centroid and square root of the area of the convex hull of all end points.

    The outline of a part is what an image shows most reliably (part against background),
    while inner edges come and go with lighting; so this normalisation agrees between a
    view and an image that misses some inner edges, where the length-weighted one drifts.
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

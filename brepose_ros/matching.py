"""Stage 4: compare an image's edge set with the views' edge sets (seed paper section 6).

For one image region and one view, both normalised for translation and scale
(``metric_space``), the distance matrix of their tetrads is solved as a bipartite
assignment with empty elements (Kuhn-Munkres, ``scipy.optimize.linear_sum_assignment``);
the matched pairs split into the nearest group and the rest; the view is ranked by its
distance sum and its nearest-pair ratio.

Where this goes beyond the paper, and why:

* In-plane rotation. The tetrad's two angles turn with the image, so the pair-wise
  matching is not rotation invariant, as the paper assumes. We search the rotation
  explicitly: the circular cross-correlation of the length-weighted orientation
  histograms of view and image (one FFT for all views) gives a few candidate rotations
  (each also turned by 180 degrees), and the assignment is solved at each candidate.
* Distance. The tetrad (l, alpha, theta, r) is compared continuously: the midpoint as a
  point (|m| and alpha together), the perpendicular as its foot point (r and theta
  together), the orientation modulo 180 degrees, and the length. Raw angle differences
  jump by 2 pi at the wrap and are meaningless at the origin; these forms do not.
* Empty elements. Leaving a segment unmatched costs the empty distance e; a pair costs
  its distance. Clipping the matrix at 2e and dropping pairs at the clip is exactly the
  assignment with empty elements inserted on both sides, at the size of the real matrix.
* Pre-filter. Kuhn-Munkres is cubic; a rotation-, scale- and translation-invariant
  histogram descriptor shortlists views before it (``ViewLibrary.shortlist``).
* The matched pairs also give a similarity transform (Procrustes on the nearest pairs),
  which corrects the image normalisation that clutter and occlusion bias.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from .metric_space import segment_lengths
from .params import MatchParams

ORIENTATION_BINS = 72  # 2.5 degree bins over [0, pi)
RADIUS_BINS = np.linspace(0.0, 2.5, 9)
LENGTH_BINS = np.array([0.0, 0.05, 0.1, 0.2, 0.35, 0.6, 1.0, 10.0])
PAIR_ANGLE_BINS = np.linspace(0.0, np.pi / 2 + 1e-9, 10)


@dataclass
class SegmentFeatures:
    """A normalised segment set in the forms the distance and the pre-filter need."""

    segments: np.ndarray  # (N, 2, 2) normalised
    lengths: np.ndarray  # (N,)
    midpoints: np.ndarray  # (N, 2)
    orientations: np.ndarray  # (N,) direction angle modulo pi
    feet: np.ndarray  # (N, 2) foot of the perpendicular from the origin to the line
    orientation_histogram: np.ndarray  # (ORIENTATION_BINS,) length-weighted, smoothed
    descriptor: np.ndarray  # rotation/scale/translation-invariant pre-filter descriptor


def longest(segments: np.ndarray, count: int) -> np.ndarray:
    """Indices of the ``count`` longest segments (all if fewer), longest first."""
    order = np.argsort(-segment_lengths(segments), kind="stable")
    return order[:count]


def describe(segments: np.ndarray) -> SegmentFeatures:
    """Features of a normalised segment set (N, 2, 2)."""
    segments = np.asarray(segments, dtype=float)
    a, b = segments[:, 0], segments[:, 1]
    d = b - a
    lengths = np.linalg.norm(d, axis=1)
    mid = (a + b) / 2.0
    orient = np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)
    unit = d / np.maximum(lengths, 1e-12)[:, None]
    feet = mid - np.sum(mid * unit, axis=1)[:, None] * unit
    hist = _orientation_histogram(orient, lengths)
    return SegmentFeatures(segments, lengths, mid, orient, feet, hist,
                           _descriptor(mid, lengths, orient))


def _orientation_histogram(orient: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    bins = (orient / np.pi * ORIENTATION_BINS).astype(int) % ORIENTATION_BINS
    hist = np.bincount(bins, weights=lengths, minlength=ORIENTATION_BINS)
    kernel = np.array([0.25, 0.5, 1.0, 0.5, 0.25])  # tolerate a few degrees of noise
    padded = np.concatenate([hist[-2:], hist, hist[:2]])
    return np.convolve(padded, kernel, mode="valid")


def _descriptor(mid: np.ndarray, lengths: np.ndarray, orient: np.ndarray) -> np.ndarray:
    """Histograms that no in-plane rotation, scale or shift changes.

    Radii of the segments' midpoints, their lengths, and the angles between pairs of
    segments, each length-weighted and normalised to sum 1.
    """
    total = max(lengths.sum(), 1e-12)
    radius = np.histogram(np.linalg.norm(mid, axis=1), RADIUS_BINS, weights=lengths)[0] / total
    length = np.histogram(lengths, LENGTH_BINS, weights=lengths)[0] / total
    top = np.argsort(-lengths)[:40]
    diff = np.abs(orient[top, None] - orient[None, top])
    diff = np.minimum(diff, np.pi - diff)
    weight = lengths[top, None] * lengths[None, top]
    pair = np.histogram(diff.ravel(), PAIR_ANGLE_BINS, weights=weight.ravel())[0]
    pair = pair / max(pair.sum(), 1e-12)
    return np.concatenate([radius, length, pair])


def rotation_candidates(view_hist: np.ndarray, image_hist: np.ndarray, count: int) -> np.ndarray:
    """Candidate in-plane rotations (radians, [0, 2 pi)) turning views onto the image.

    view_hist is (V, B): one circular cross-correlation per view by FFT. Each of the
    ``count`` best peaks (modulo pi) gives two candidates, phi and phi + pi. Returns (V, 2*count).
    """
    spectrum = np.fft.rfft(image_hist)[None, :] * np.conj(np.fft.rfft(view_hist, axis=1))
    corr = np.fft.irfft(spectrum, n=ORIENTATION_BINS, axis=1)
    is_peak = (corr >= np.roll(corr, 1, axis=1)) & (corr >= np.roll(corr, -1, axis=1))
    ranked = np.argsort(-np.where(is_peak, corr, -np.inf), axis=1)[:, :count]
    phi = ranked * (np.pi / ORIENTATION_BINS)
    return np.concatenate([phi, phi + np.pi], axis=1)


def distance_matrix(model: SegmentFeatures, image: SegmentFeatures, phi: float, p: MatchParams) -> np.ndarray:
    """(n_model, n_image) tetrad distances with the model turned by ``phi``."""
    c, s = np.cos(phi), np.sin(phi)
    rot = np.array([[c, -s], [s, c]])
    m_mid = model.midpoints @ rot.T
    m_feet = model.feet @ rot.T
    d_len = model.lengths[:, None] - image.lengths[None, :]
    d_mid = m_mid[:, None, :] - image.midpoints[None, :, :]
    d_feet = m_feet[:, None, :] - image.feet[None, :, :]
    d_ori = np.mod(model.orientations[:, None] + phi - image.orientations[None, :] + np.pi / 2, np.pi) - np.pi / 2
    squared = (p.weight_length * d_len**2
               + p.weight_midpoint * np.einsum("ijk,ijk->ij", d_mid, d_mid)
               + p.weight_orientation * d_ori**2
               + p.weight_perpendicular * np.einsum("ijk,ijk->ij", d_feet, d_feet))
    return np.sqrt(squared)


@dataclass
class Assignment:
    """Kuhn-Munkres result for one (view, rotation) against one image region."""

    cost: float  # distance sum with empty elements, per element of both sets
    model_index: np.ndarray  # matched pairs (not empty), indices into the view's features
    image_index: np.ndarray
    distances: np.ndarray
    nearest: np.ndarray  # bool per matched pair: in the nearest group
    n_model: int
    empty_distance: float

    @property
    def error_ratio(self) -> float:
        """Share of the view's model edges outside the nearest group (CONVENTIONS.md)."""
        return 1.0 - float(self.nearest.sum()) / max(self.n_model, 1)


def assign(model: SegmentFeatures, image: SegmentFeatures, phi: float, p: MatchParams) -> Assignment:
    """Bipartite matching with empty elements on both sides.

    As in the paper, the empty distance is tied to the largest distance of the matrix
    (``empty_coefficient`` times it); pairs in the nearest group are closer than
    ``nearest_threshold`` times the empty distance.
    """
    dist = distance_matrix(model, image, phi, p)
    empty_distance = p.empty_coefficient * float(dist.max())
    clip = 2.0 * empty_distance
    rows, cols = linear_sum_assignment(np.minimum(dist, clip))
    pair_dist = dist[rows, cols]
    real = pair_dist < clip
    rows, cols, pair_dist = rows[real], cols[real], pair_dist[real]
    n_m, n_i = dist.shape
    unmatched = (n_m - len(rows)) + (n_i - len(cols))
    cost = (pair_dist.sum() + empty_distance * unmatched) / (n_m + n_i)
    nearest = pair_dist < p.nearest_threshold * empty_distance
    return Assignment(float(cost), rows, cols, pair_dist, nearest, n_m, empty_distance)


def similarity_from_pairs(model: SegmentFeatures, image: SegmentFeatures,
                          assignment: Assignment) -> tuple[float, float, np.ndarray] | None:
    """Scale, rotation and shift mapping model to image points, from the nearest pairs.

    Weighted 2D Procrustes (Umeyama) over the matched segments' end points, each pair's
    end points taken in the order that fits best. None with fewer than two nearest pairs.
    """
    keep = assignment.nearest
    if keep.sum() < 2:
        return None
    src = model.segments[assignment.model_index[keep]]
    dst = image.segments[assignment.image_index[keep]]
    straight = np.sum((src - dst) ** 2, axis=(1, 2))
    swapped = np.sum((src - dst[:, ::-1]) ** 2, axis=(1, 2))
    dst = np.where((swapped < straight)[:, None, None], dst[:, ::-1], dst)
    weights = np.repeat(np.minimum(model.lengths[assignment.model_index[keep]],
                                   image.lengths[assignment.image_index[keep]]), 2)
    src, dst = src.reshape(-1, 2), dst.reshape(-1, 2)
    return weighted_similarity(src, dst, weights)


def weighted_similarity(src: np.ndarray, dst: np.ndarray, weights: np.ndarray):
    """(scale, angle, shift) minimising sum w |scale R(angle) src + shift - dst|^2."""
    w = weights / max(weights.sum(), 1e-12)
    mu_s, mu_d = w @ src, w @ dst
    a, b = src - mu_s, dst - mu_d
    var = float(w @ np.sum(a * a, axis=1))
    if var <= 1e-12:
        return None
    cross = (w[:, None] * a).T @ b  # 2x2
    angle = np.arctan2(cross[0, 1] - cross[1, 0], cross[0, 0] + cross[1, 1])
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    scale = float(np.sum((rot @ a.T).T * b * w[:, None]) / var)
    if scale <= 0:
        return None
    return scale, float(angle), mu_d - scale * rot @ mu_s

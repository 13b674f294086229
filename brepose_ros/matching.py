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
* Pre-filter. Kuhn-Munkres is cubic, so it does not run for every view: points sampled
  along every view's segments, turned by each view's candidate rotations, look up an
  oriented distance map of the image region (all views at once, ``ChamferPrefilter``);
  the closest (view, rotation) pairs go on to the assignment.
* The matched pairs also give a similarity transform (Procrustes on the nearest pairs),
  which corrects the image normalisation that clutter and occlusion bias.
* Ranking. After that alignment, views are ranked by how much of the view's and of the
  region's edge length the other set covers (``coverage``, an F-measure). On rendered
  sharp brackets, the view with the lowest distance sum was within 15 degrees of the
  truth for 4 of 12 images, the one with the best coverage for 10 of 12; the distance
  sum and the nearest-pair ratio are still reported (score, error ratio).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from .metric_space import segment_lengths
from .params import MatchParams
from .pose import line_equations, nearest_lines

ORIENTATION_BINS = 72  # 2.5 degree bins over [0, pi)


@dataclass
class SegmentFeatures:
    """A normalised segment set in the forms the distance and the pre-filter need."""

    segments: np.ndarray  # (N, 2, 2) normalised
    lengths: np.ndarray  # (N,)
    midpoints: np.ndarray  # (N, 2)
    orientations: np.ndarray  # (N,) direction angle modulo pi
    feet: np.ndarray  # (N, 2) foot of the perpendicular from the origin to the line
    orientation_histogram: np.ndarray  # (ORIENTATION_BINS,) length-weighted, smoothed


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
    return SegmentFeatures(segments, lengths, mid, orient, feet, hist)


def _orientation_histogram(orient: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    bins = (orient / np.pi * ORIENTATION_BINS).astype(int) % ORIENTATION_BINS
    hist = np.bincount(bins, weights=lengths, minlength=ORIENTATION_BINS)
    kernel = np.array([0.25, 0.5, 1.0, 0.5, 0.25])  # tolerate a few degrees of noise
    padded = np.concatenate([hist[-2:], hist, hist[:2]])
    return np.convolve(padded, kernel, mode="valid")


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


def similarity_from_pairs(model: SegmentFeatures, image: SegmentFeatures, assignment: Assignment,
                          phi: float) -> tuple[float, float, np.ndarray] | None:
    """Scale, rotation and shift mapping model to image points, from the nearest pairs.

    Weighted 2D Procrustes (Umeyama) over the matched segments' end points, each pair's
    end points taken in the order that fits best once the model is turned by ``phi``, the
    rotation the pairs were matched at. None with fewer than two nearest pairs.
    """
    keep = assignment.nearest
    if keep.sum() < 2:
        return None
    src = model.segments[assignment.model_index[keep]]
    dst = image.segments[assignment.image_index[keep]]
    turned = apply_similarity(src, 1.0, phi, np.zeros(2))
    straight = np.sum((turned - dst) ** 2, axis=(1, 2))
    swapped = np.sum((turned - dst[:, ::-1]) ** 2, axis=(1, 2))
    dst = np.where((swapped < straight)[:, None, None], dst[:, ::-1], dst)
    weights = np.repeat(np.minimum(model.lengths[assignment.model_index[keep]],
                                   image.lengths[assignment.image_index[keep]]), 2)
    src, dst = src.reshape(-1, 2), dst.reshape(-1, 2)
    return weighted_similarity(src, dst, weights)


def apply_similarity(segments: np.ndarray, scale: float, angle: float, shift: np.ndarray) -> np.ndarray:
    """Points or segments (..., 2) mapped by scale * R(angle) x + shift."""
    c, s = np.cos(angle), np.sin(angle)
    return scale * np.asarray(segments) @ np.array([[c, s], [-s, c]]) + shift


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


def point_segment_distance(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(P, S) distances of points to segments (x and y kept apart: numpy's overhead on
    (P, S, 2) arrays cost more than the arithmetic)."""
    a, b = segments[:, 0], segments[:, 1]
    dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
    dd = np.maximum(dx * dx + dy * dy, 1e-18)
    px, py = points[:, :1], points[:, 1:]
    u = np.clip(((px - a[:, 0]) * dx + (py - a[:, 1]) * dy) / dd, 0.0, 1.0)
    ex, ey = px - (a[:, 0] + u * dx), py - (a[:, 1] + u * dy)
    return np.sqrt(ex * ex + ey * ey)


def coverage(source: np.ndarray, target: np.ndarray, tolerance: float, max_angle_deg: float = 12.0,
             per_segment: int = 4) -> float:
    """Share of the length of ``source`` segments lying within ``tolerance`` of a parallel
    ``target`` segment: an oriented chamfer test in the normalised frame, on
    ``per_segment`` points per source segment."""
    if len(source) == 0 or len(target) == 0:
        return 0.0
    su = source[:, 1] - source[:, 0]
    tu = target[:, 1] - target[:, 0]
    s_len = np.sqrt(su[:, 0] * su[:, 0] + su[:, 1] * su[:, 1])
    t_len = np.sqrt(tu[:, 0] * tu[:, 0] + tu[:, 1] * tu[:, 1])
    cos = np.abs(su @ tu.T) / np.maximum(np.outer(s_len, t_len), 1e-18)
    frac = (np.arange(per_segment) + 0.5) / per_segment
    points = (source[:, None, 0] + frac[None, :, None] * su[:, None]).reshape(-1, 2)
    near = point_segment_distance(points, target).reshape(len(source), per_segment, -1) < tolerance
    covered = (near & (cos > np.cos(np.radians(max_angle_deg)))[:, None]).any(axis=2).ravel()
    weight = np.repeat(s_len / per_segment, per_segment)
    return float(weight[covered].sum() / max(weight.sum(), 1e-18))


class ChamferPrefilter:
    """Oriented chamfer distance of every view, at its candidate rotations, to a region.

    Views are sampled once as ``points_per_view`` points along their normalised segments
    (length-weighted). A region is rasterised once into ``ORIENT_BINS`` distance maps, one
    per edge direction, over the normalised square [-EXTENT, EXTENT]^2. Scoring every
    (view, rotation) is then a gather over a (V, R, P) index array: a few milliseconds for
    thousands of views.
    """

    ORIENT_BINS = 6
    GRID = 96
    EXTENT = 2.0
    TRUNCATE = 0.25
    BLOCK = 256

    def __init__(self, view_features: list[SegmentFeatures], points_per_view: int = 32):
        pts, ori = [], []
        for f in view_features:
            p, o = _spread_points(f.segments, points_per_view)
            pts.append(p)
            ori.append(o)
        self.points = np.stack(pts).astype(np.float32)  # (V, P, 2)
        self.orientations = np.stack(ori).astype(np.float32)  # (V, P) modulo pi

    def distance_maps(self, region: SegmentFeatures) -> np.ndarray:
        cell = 2.0 * self.EXTENT / self.GRID
        maps = np.empty((self.ORIENT_BINS, self.GRID, self.GRID), np.float32)
        bins = (region.orientations / np.pi * self.ORIENT_BINS).astype(int) % self.ORIENT_BINS
        ends = np.round((region.segments + self.EXTENT) / cell).astype(np.int32)
        for b in range(self.ORIENT_BINS):
            canvas = np.full((self.GRID, self.GRID), 255, np.uint8)
            cv2.polylines(canvas, list(ends[bins == b]), False, 0, 1)
            maps[b] = cv2.distanceTransform(canvas, cv2.DIST_L2, 3) * cell
        return np.minimum(maps, self.TRUNCATE)

    def scores(self, maps: np.ndarray, phis: np.ndarray) -> np.ndarray:
        """(V, R) mean truncated oriented distance of view v turned by phis[v, r].

        Every step is over V x R x P points (10^5 to 10^6), so it runs in blocks of
        ``BLOCK`` views, whose temporaries stay in the cache, and the slow steps are
        avoided: one flat gather instead of a 3-index one, and no np.mod for the
        orientation (with phi in [0, 2 pi) the turned orientation is below 3 pi, and
        subtracting pi once or twice gives np.mod's result to the bit).
        """
        phis = np.mod(phis.astype(np.float32), np.float32(2 * np.pi))
        out = np.empty(phis.shape, np.float32)
        for lo in range(0, len(phis), self.BLOCK):
            views = slice(lo, lo + self.BLOCK)
            out[views] = self._block_scores(maps, self.points[views], self.orientations[views], phis[views])
        return out

    def _block_scores(self, maps, points, orientations, phis):
        c, s = np.cos(phis)[..., None], np.sin(phis)[..., None]
        x, y = points[:, None, :, 0], points[:, None, :, 1]
        xr, yr = c * x - s * y, s * x + c * y  # (V, R, P)
        cell = 2.0 * self.EXTENT / self.GRID
        col = np.clip(((xr + self.EXTENT) / cell).astype(np.int32), 0, self.GRID - 1)
        row = np.clip(((yr + self.EXTENT) / cell).astype(np.int32), 0, self.GRID - 1)
        ori = orientations[:, None, :] + phis[..., None]
        half_turns = (ori >= np.float32(np.pi)).astype(np.float32) + (ori >= np.float32(2 * np.pi))
        ori -= np.float32(np.pi) * half_turns
        b = (ori / np.pi * self.ORIENT_BINS).astype(np.int32) % self.ORIENT_BINS
        outside = (np.abs(xr) > self.EXTENT) | (np.abs(yr) > self.EXTENT)
        dist = np.where(outside, self.TRUNCATE, maps.ravel()[(b * self.GRID + row) * self.GRID + col])
        return dist.mean(axis=2)


def _spread_points(segments: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points evenly spaced along the total length of a segment set."""
    lengths = segment_lengths(segments)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    at = (np.arange(count) + 0.5) / count * cum[-1]
    idx = np.clip(np.searchsorted(cum, at, side="right") - 1, 0, len(segments) - 1)
    frac = (at - cum[idx]) / np.maximum(lengths[idx], 1e-12)
    a, b = segments[idx, 0], segments[idx, 1]
    d = b - a
    return a + frac[:, None] * d, np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)


def align_to_lines(model: np.ndarray, image: np.ndarray, tolerances: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """2D ICP on segments: a similarity pulling ``model`` end points onto their nearest
    image lines, re-associating at each tolerance in turn (normalised units).

    The similarity x' = [[p, -q], [q, p]] x + b is linear in (p, q, bx, by), and so is
    the distance of x' to a line: each round is one 4x4 least-squares solve. Returns the
    moved model segments and the 2x3 similarity matrix applied to them.
    """
    total = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    moved = model
    lines = line_equations(image)
    for tolerance in tolerances:
        mi, ii, _ = nearest_lines(moved, image, tolerance)
        if len(mi) < 3:
            break
        nx, ny, c = np.repeat(lines[ii], 2, axis=0).T
        matched = moved[mi]
        x, y = matched.reshape(-1, 2).T
        weights = np.repeat(segment_lengths(matched), 2)
        rows = np.array([nx * x + ny * y, -nx * y + ny * x, nx, ny]) * weights
        solution = np.linalg.lstsq(rows.T, -c * weights, rcond=None)[0]
        p, q, bx, by = solution
        if not np.isfinite(solution).all() or np.hypot(p, q) < 1e-6:
            break
        step = np.array([[p, -q, bx], [q, p, by]])
        moved = moved @ step[:, :2].T + step[:, 2]
        total = step[:, :2] @ total
        total[:, 2] += step[:, 2]
    return moved, total

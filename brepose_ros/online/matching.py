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
  the closest (view, rotation) pairs go on to the assignment. The map is drawn from the
  region's Canny edge pixels, not from its line segments: holes, fillets and rounded
  outlines give no segment but do give edge pixels, and the view's chords of those curves
  then find their counterpart. Measured on bench scenes (24 + 12 images per part, seeds
  100 and 200): clean successes 111 -> 119 of 144 (the SO-ARM100 base attachment, full of
  holes, 21 -> 28 of 36), clutter 50 -> 59 and 30 % occlusion 1 -> 4 of 96.
* The matched pairs also give a similarity transform (Procrustes on the nearest pairs),
  which corrects the image normalisation that clutter and occlusion bias.
* Ranking. After that alignment, views are ranked by how much of the view's and of the
  region's edge length the other set covers (``coverage``, an F-measure). On rendered
  sharp brackets, the view with the lowest distance sum was within 15 degrees of the
  truth for 4 of 12 images, the one with the best coverage for 10 of 12; the distance
  sum and the nearest-pair ratio are still reported (score, error ratio).
* Batches. The jobs of one region (the pre-filter's (view, rotation) pairs) run
  together: the views' segment sets are zero-padded to one size (``SegmentBatch``) and
  every step but Kuhn-Munkres, which runs per job on its real rows, is one array
  operation for all jobs. Job by job, each job was ~40 small numpy calls whose overhead
  was much of its time. Distance matrices and assignments equal the job-by-job ones to
  the bit; the similarities agree to about 1e-11 (sums in another order).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from ..metric_space import segment_lengths
from ..params import MatchParams
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
    lengths, mid, orient, feet = _geometry(segments)
    return SegmentFeatures(segments, lengths, mid, orient, feet, _orientation_histogram(orient, lengths))


def _geometry(segments: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lengths, midpoints, orientations modulo pi and perpendicular feet of segments (..., 2, 2)."""
    a, b = segments[..., 0, :], segments[..., 1, :]
    d = b - a
    lengths = np.linalg.norm(d, axis=-1)
    mid = (a + b) / 2.0
    orient = np.mod(np.arctan2(d[..., 1], d[..., 0]), np.pi)
    unit = d / np.maximum(lengths, 1e-12)[..., None]
    feet = mid - np.sum(mid * unit, axis=-1)[..., None] * unit
    return lengths, mid, orient, feet


@dataclass
class SegmentBatch:
    """Segment sets of different sizes, one per matching job, zero-padded to one size M.

    All (view, rotation) jobs of one image region then run as a few operations on
    (J, M, ...) arrays instead of dozens of small numpy calls each, whose overhead cost
    more than their arithmetic. Set j owns the first ``counts[j]`` entries; the functions
    below never let the padding (finite, masked by ``valid``) reach a result.
    """

    segments: np.ndarray  # (J, M, 2, 2)
    valid: np.ndarray  # (J, M) bool
    lengths: np.ndarray  # (J, M)
    midpoints: np.ndarray  # (J, M, 2)
    orientations: np.ndarray  # (J, M) modulo pi
    feet: np.ndarray  # (J, M, 2)

    @classmethod
    def of(cls, segments: np.ndarray, valid: np.ndarray) -> "SegmentBatch":
        return cls(segments, valid, *_geometry(segments))

    @classmethod
    def pad(cls, sets: list[np.ndarray], size: int) -> "SegmentBatch":
        """The sets padded to ``size`` segments: a fixed size, not the batch's largest set,
        keeps every set's sums in the same order however the jobs are batched."""
        counts = np.array([len(s) for s in sets])
        valid = np.arange(size) < counts[:, None]
        segments = np.zeros(valid.shape + (2, 2))
        segments[valid] = np.concatenate(sets)
        return cls.of(segments, valid)

    @property
    def counts(self) -> np.ndarray:
        return self.valid.sum(axis=1)


def take(batch, jobs):
    """A batch dataclass (``SegmentBatch``, ``Assignment``, ``Similarity``) reduced to some jobs."""
    return dataclasses.replace(batch, **{f.name: getattr(batch, f.name)[jobs] for f in dataclasses.fields(batch)})


def _orientation_histogram(orient: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    bins = (orient / np.pi * ORIENTATION_BINS).astype(int) % ORIENTATION_BINS
    hist = np.bincount(bins, weights=lengths, minlength=ORIENTATION_BINS)
    kernel = np.array([0.25, 0.5, 1.0, 0.5, 0.25])  # tolerate a few degrees of noise
    padded = np.concatenate([hist[-2:], hist, hist[:2]])
    return np.convolve(padded, kernel, mode="valid")


def orientation_spectra(view_hist: np.ndarray) -> np.ndarray:
    """Conjugate spectra of view orientation histograms (V, B) for ``rotation_candidates``:
    the views' half of the cross-correlation, computed once when the views are loaded."""
    return np.conj(np.fft.rfft(view_hist, axis=1))


def rotation_candidates(view_spectra: np.ndarray, image_hist: np.ndarray, count: int) -> np.ndarray:
    """Candidate in-plane rotations (radians, [0, 2 pi)) turning views onto the image.

    view_spectra is ``orientation_spectra`` of the (V, B) view histograms: one circular
    cross-correlation per view by one inverse FFT. Each of the ``count`` best peaks
    (modulo pi) gives two candidates, phi and phi + pi. Returns (V, 2*count). Per region at
    2,500 views this takes 3.5 ms; with the views' FFT done here and the peaks ranked by a
    full argsort it took 11 ms, for the same candidates.
    """
    corr = np.fft.irfft(np.fft.rfft(image_hist)[None, :] * view_spectra, n=ORIENTATION_BINS, axis=1)
    wrapped = np.concatenate([corr[:, -1:], corr, corr[:, :1]], axis=1)
    peaks = np.where((corr >= wrapped[:, :-2]) & (corr >= wrapped[:, 2:]), corr, -np.inf)
    ranked = np.empty((len(corr), count), dtype=int)
    rows = np.arange(len(corr))
    for k in range(count):  # best peak first, then the next best: a few argmax, no sort
        ranked[:, k] = best = np.argmax(peaks, axis=1)
        peaks[rows, best] = -np.inf
    phi = ranked * (np.pi / ORIENTATION_BINS)
    return np.concatenate([phi, phi + np.pi], axis=1)


def distance_matrix(model: SegmentBatch, image: SegmentFeatures, phi: np.ndarray, p: MatchParams) -> np.ndarray:
    """(J, M, n_image) tetrad distances, set j of the model turned by ``phi[j]``."""
    turn = rotations(phi).transpose(0, 2, 1)
    squared = p.weight_length * (model.lengths[..., None] - image.lengths) ** 2
    squared += p.weight_midpoint * _squared_distances(model.midpoints @ turn, image.midpoints)
    d_ori = _mod_pi(model.orientations[..., None] + phi[:, None, None] - image.orientations + np.pi / 2) - np.pi / 2
    squared += p.weight_orientation * d_ori**2
    squared += p.weight_perpendicular * _squared_distances(model.feet @ turn, image.feet)
    return np.sqrt(squared, out=squared)


def _squared_distances(points: np.ndarray, others: np.ndarray) -> np.ndarray:
    """(..., M, N) squared distances of points (..., M, 2) to others (N, 2)."""
    dx = points[..., 0, None] - others[:, 0]
    dy = points[..., 1, None] - others[:, 1]
    return dx * dx + dy * dy


def _mod_pi(x: np.ndarray) -> np.ndarray:
    """np.mod(x, pi) to the bit for x in [-pi, 4 pi), at half its cost (its fmod is slow).

    Where x >= 2 pi, x - 2 pi is exact: it is np.mod's result or, for x >= 3 pi, lies in
    [pi, 2 pi) on a grid fine enough to hold it; then x - pi is exact on [pi, 2 pi), and
    below 0 np.mod adds pi with the same rounding. Other x take np.mod itself.
    """
    if not (x.min(initial=0.0) >= -np.pi and x.max(initial=0.0) < 4 * np.pi):
        return np.mod(x, np.pi)
    x = x.copy()
    np.subtract(x, 2 * np.pi, out=x, where=x >= 2 * np.pi)
    np.subtract(x, np.pi, out=x, where=x >= np.pi)
    np.add(x, np.pi, out=x, where=x < 0)
    return x


def rotations(angle: np.ndarray) -> np.ndarray:
    """(J, 2, 2) rotation matrices [[c, -s], [s, c]]."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c, -s, s, c], axis=-1).reshape(np.shape(angle) + (2, 2))


@dataclass
class Assignment:
    """Kuhn-Munkres results of a batch of (view, rotation) jobs against one image region."""

    cost: np.ndarray  # (J,) distance sum with empty elements, per element of both sets
    image_index: np.ndarray  # (J, M) image segment paired with each model segment, -1 if empty
    distances: np.ndarray  # (J, M) distance of each pair
    nearest: np.ndarray  # (J, M) bool: the pair is in the nearest group
    n_model: np.ndarray  # (J,)
    empty_distance: np.ndarray  # (J,)

    @property
    def error_ratio(self) -> np.ndarray:
        """Share of the view's model edges outside the nearest group (CONVENTIONS.md)."""
        return 1.0 - self.nearest.sum(axis=1) / np.maximum(self.n_model, 1)


def assign(model: SegmentBatch, image: SegmentFeatures, phi: np.ndarray, p: MatchParams) -> Assignment:
    """Bipartite matching with empty elements on both sides, for each set of the batch.

    As in the paper, the empty distance is tied to the largest distance of the matrix
    (``empty_coefficient`` times it; over the set's real segments only); pairs in the
    nearest group are closer than ``nearest_threshold`` times the empty distance.
    Kuhn-Munkres runs per set, on its real rows.
    """
    dist = distance_matrix(model, image, phi, p)
    empty_distance = p.empty_coefficient * np.where(model.valid[..., None], dist, 0.0).max(axis=(1, 2))
    clip = 2.0 * empty_distance
    clipped = np.minimum(dist, clip[:, None, None])
    image_index = np.full(model.valid.shape, -1)
    n_model = model.counts
    for j, rows in enumerate(n_model):
        matched_rows, cols = linear_sum_assignment(clipped[j, :rows])
        image_index[j, matched_rows] = cols
    pair_dist = np.take_along_axis(dist, np.maximum(image_index, 0)[..., None], axis=2)[..., 0]
    real = (image_index >= 0) & (pair_dist < clip[:, None])
    image_index[~real] = -1
    n_pairs = real.sum(axis=1)
    unmatched = (n_model - n_pairs) + (dist.shape[2] - n_pairs)
    cost = (np.where(real, pair_dist, 0.0).sum(axis=1) + empty_distance * unmatched) / (n_model + dist.shape[2])
    nearest = real & (pair_dist < p.nearest_threshold * empty_distance[:, None])
    return Assignment(cost, image_index, pair_dist, nearest, n_model, empty_distance)


@dataclass
class Similarity:
    """Similarities x -> scale R(angle) x + shift, one per job; ``found`` is False where the
    pairs did not determine one."""

    scale: np.ndarray  # (J,)
    angle: np.ndarray  # (J,)
    shift: np.ndarray  # (J, 2)
    found: np.ndarray  # (J,) bool


def similarity_from_pairs(model: SegmentBatch, image: SegmentFeatures, assignment: Assignment,
                          phi: np.ndarray) -> Similarity:
    """Scale, rotation and shift mapping each model set to image points, from its nearest pairs.

    Weighted 2D Procrustes (Umeyama) over the matched segments' end points, each pair's
    end points taken in the order that fits best once the model is turned by ``phi``, the
    rotation the pairs were matched at. Not found with fewer than two nearest pairs.
    """
    keep = assignment.nearest
    index = np.maximum(assignment.image_index, 0)
    src, dst = model.segments, image.segments[index]
    turned = apply_similarity(src, np.ones(len(phi)), phi, np.zeros((len(phi), 2)))
    straight = np.sum((turned - dst) ** 2, axis=(2, 3))
    swapped = np.sum((turned - dst[:, :, ::-1]) ** 2, axis=(2, 3))
    dst = np.where((swapped < straight)[..., None, None], dst[:, :, ::-1], dst)
    weights = np.repeat(np.where(keep, np.minimum(model.lengths, image.lengths[index]), 0.0), 2, axis=1)
    n_sets = len(src)
    similarity = weighted_similarity(src.reshape(n_sets, -1, 2), dst.reshape(n_sets, -1, 2), weights)
    similarity.found &= keep.sum(axis=1) >= 2
    return similarity


def apply_similarity(segments: np.ndarray, scale: np.ndarray, angle: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Points or segments (J, ..., 2) mapped by scale[j] * R(angle[j]) x + shift[j]."""
    segments = np.asarray(segments)
    moved = scale[:, None, None] * segments.reshape(len(segments), -1, 2) @ rotations(angle).transpose(0, 2, 1)
    return _shifted(moved, shift).reshape(segments.shape)


def _shifted(points: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """points (J, P, 2) + shift (J, 2), in place and one coordinate at a time: numpy
    broadcasts slowly over a last axis of length 2."""
    points[..., 0] += shift[:, 0, None]
    points[..., 1] += shift[:, 1, None]
    return points


def weighted_similarity(src: np.ndarray, dst: np.ndarray, weights: np.ndarray) -> Similarity:
    """Per set j, (scale, angle, shift) minimising sum w |scale R(angle) src + shift - dst|^2
    over points (J, P, 2) with weights (J, P); not found where the source points do not
    spread or the scale is not positive."""
    w = weights / np.maximum(weights.sum(axis=1), 1e-12)[:, None]
    mu_s, mu_d = np.einsum("jp,jpk->jk", w, src), np.einsum("jp,jpk->jk", w, dst)
    a, b = src - mu_s[:, None], dst - mu_d[:, None]
    var = np.einsum("jp,jp->j", w, np.sum(a * a, axis=2))
    cross = (w[..., None] * a).transpose(0, 2, 1) @ b  # (J, 2, 2)
    angle = np.arctan2(cross[:, 0, 1] - cross[:, 1, 0], cross[:, 0, 0] + cross[:, 1, 1])
    rot = rotations(angle)
    spread = var > 1e-12
    scale = np.einsum("jpk,jpk,jp->j", a @ rot.transpose(0, 2, 1), b, w) / np.where(spread, var, 1.0)
    shift = mu_d - scale[:, None] * np.einsum("jkl,jl->jk", rot, mu_s)
    return Similarity(scale, angle, shift, spread & (scale > 0))


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


def coverage(model: np.ndarray, valid: np.ndarray, image: np.ndarray, tolerance: float,
             max_angle_deg: float = 12.0, per_segment: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Two-way edge coverage of each model set (J, M, 2, 2; ``valid`` marks real segments)
    and the image segments: the share of the set's length, and the share of the image's,
    lying within ``tolerance`` of a parallel segment of the other side. An oriented chamfer
    test in the normalised frame, on ``per_segment`` points per segment.

    Only a few (model, image) pairs can cover: parallel ones whose bounding boxes lie
    closer than the tolerance (plus a margin far above rounding); distances are measured
    for those pairs only.
    """
    sets = np.nonzero(valid)[0]
    flat = model[valid]
    fu, iu = flat[:, 1] - flat[:, 0], image[:, 1] - image[:, 0]
    f_len = np.sqrt(fu[:, 0] * fu[:, 0] + fu[:, 1] * fu[:, 1])
    i_len = np.sqrt(iu[:, 0] * iu[:, 0] + iu[:, 1] * iu[:, 1])
    cos = np.abs(fu @ iu.T) / np.maximum(np.outer(f_len, i_len), 1e-18)
    f_lo, f_hi = np.minimum(flat[:, 0], flat[:, 1]), np.maximum(flat[:, 0], flat[:, 1])
    i_lo, i_hi = np.minimum(image[:, 0], image[:, 1]), np.maximum(image[:, 0], image[:, 1])
    gap = np.maximum(np.maximum(f_lo[:, None, 0] - i_hi[:, 0], i_lo[:, 0] - f_hi[:, None, 0]),
                     np.maximum(f_lo[:, None, 1] - i_hi[:, 1], i_lo[:, 1] - f_hi[:, None, 1]))
    fi, ii = np.nonzero((cos > np.cos(np.radians(max_angle_deg))) & (gap < tolerance * (1 + 1e-6)))
    frac = (np.arange(per_segment) + 0.5) / per_segment
    covered_model = np.zeros((len(flat), per_segment), bool)
    point, pair = np.nonzero(_near_points(flat[fi], image[ii], frac, tolerance))
    covered_model[fi[pair], point] = True
    covered_image = np.zeros((len(model), len(image), per_segment), bool)
    point, pair = np.nonzero(_near_points(image[ii], flat[fi], frac, tolerance))
    covered_image[sets[fi[pair]], ii[pair], point] = True
    n_sets = len(model)
    model_share = (np.bincount(sets, covered_model.sum(axis=1) * (f_len / per_segment), n_sets)
                   / np.maximum(np.bincount(sets, f_len, n_sets), 1e-18))
    image_share = (covered_image.sum(axis=2) * (i_len / per_segment)).sum(axis=1) / max(i_len.sum(), 1e-18)
    return model_share, image_share


def _near_points(source: np.ndarray, target: np.ndarray, frac: np.ndarray, tolerance: float) -> np.ndarray:
    """(len(frac), P) bool: the point at frac[k] along source[p] lies within ``tolerance``
    of target[p]."""
    start, direction = source[:, 0], source[:, 1] - source[:, 0]
    return point_segment_distance(start + frac[:, None, None] * direction, target) < tolerance


class ChamferPrefilter:
    """Oriented chamfer distance of every view, at its candidate rotations, to a region.

    Views are sampled once as ``points_per_view`` points along their normalised segments
    (length-weighted). A region's oriented edge points (normalised, e.g. its edge pixels)
    are rasterised once into ``ORIENT_BINS`` distance maps, one per edge direction, over
    the normalised square [-EXTENT, EXTENT]^2. Scoring every (view, rotation) is then a
    gather over a (V, R, P) index array: a few milliseconds for thousands of views.
    """

    ORIENT_BINS = 6
    GRID = 96
    EXTENT = 2.0
    TRUNCATE = 0.25
    BLOCK = 256
    COARSE_STRIDE = 4
    COARSE_KEEP = 16

    def __init__(self, view_features: list[SegmentFeatures], points_per_view: int = 32):
        pts, ori = [], []
        for f in view_features:
            p, o = spread_points(f.segments, points_per_view)
            pts.append(p)
            ori.append(o)
        self.points = np.stack(pts).astype(np.float32)  # (V, P, 2)
        self.orientations = np.stack(ori).astype(np.float32)  # (V, P) modulo pi

    def distance_maps(self, points: np.ndarray, orientations: np.ndarray) -> np.ndarray:
        """(ORIENT_BINS, GRID, GRID) truncated distance to the region's points (N, 2) of each
        direction bin (orientations modulo pi); a point falls in the cell the gather of
        ``scores`` reads, and points outside the square are left out."""
        cell = 2.0 * self.EXTENT / self.GRID
        col, row = np.floor((np.asarray(points, dtype=float) + self.EXTENT) / cell).astype(np.int64).T
        inside = (col >= 0) & (col < self.GRID) & (row >= 0) & (row < self.GRID)
        bins = (np.asarray(orientations)[inside] / np.pi * self.ORIENT_BINS).astype(int) % self.ORIENT_BINS
        canvas = np.full((self.ORIENT_BINS, self.GRID, self.GRID), 255, np.uint8)
        canvas[bins, row[inside], col[inside]] = 0
        maps = np.stack([cv2.distanceTransform(c, cv2.DIST_L2, 3) for c in canvas]) * np.float32(cell)
        return np.minimum(maps, np.float32(self.TRUNCATE))

    def shortlist(self, maps: np.ndarray, phis: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
        """Views and rotation indices (in no particular order) of the ``count`` (view,
        rotation) pairs with the lowest score.

        Two stages: every pair is scored on every ``COARSE_STRIDE``-th of its points (still
        spread along the whole view), and only the ``COARSE_KEEP`` x ``count`` best go on to
        the full score. At 10,000 views this is what keeps the pre-filter affordable.
        """
        coarse = self.scores(maps, phis, slice(None, None, self.COARSE_STRIDE)).ravel()
        keep = min(len(coarse), self.COARSE_KEEP * count)
        pairs = np.argpartition(coarse, keep - 1)[:keep] if keep < len(coarse) else np.arange(len(coarse))
        views, which = np.unravel_index(pairs, phis.shape)
        fine = self._block_scores(maps, self.points[views], self.orientations[views],
                                  np.mod(phis[views, which].astype(np.float32), np.float32(2 * np.pi))[:, None])[:, 0]
        count = min(count, len(fine))
        best = np.argpartition(fine, count - 1)[:count]
        return views[best], which[best]

    def scores(self, maps: np.ndarray, phis: np.ndarray, points: slice = slice(None)) -> np.ndarray:
        """(V, R) mean truncated oriented distance of view v turned by phis[v, r], over the
        view's ``points`` (all by default).

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
            out[views] = self._block_scores(maps, self.points[views, points], self.orientations[views, points],
                                            phis[views])
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


def spread_points(segments: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points evenly spaced along the total length of a segment set, and the
    orientation (modulo pi) of the segment each lies on."""
    lengths = segment_lengths(segments)
    cum = np.concatenate([[0.0], np.cumsum(lengths)])
    at = (np.arange(count) + 0.5) / count * cum[-1]
    idx = np.clip(np.searchsorted(cum, at, side="right") - 1, 0, len(segments) - 1)
    frac = (at - cum[idx]) / np.maximum(lengths[idx], 1e-12)
    a, b = segments[idx, 0], segments[idx, 1]
    d = b - a
    return a + frac[:, None] * d, np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi)


def align_to_lines(model: np.ndarray, valid: np.ndarray, image: np.ndarray,
                   tolerances: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """2D ICP on segments: per set of ``model`` (J, M, 2, 2; ``valid`` marks its real
    segments), a similarity pulling its end points onto their nearest image lines,
    re-associating at each tolerance in turn (normalised units).

    The similarity x' = [[p, -q], [q, p]] x + b is linear in (p, q, bx, by), and so is
    the distance of x' to a line: each round is one 4x4 least-squares solve per set. A set
    stops when fewer than three of its segments find a line or the solve degenerates.
    Returns the moved model segments and the (J, 2, 3) similarity matrices applied to them.
    """
    n_sets = len(model)
    total = np.tile(np.eye(2, 3), (n_sets, 1, 1))
    moved = model
    lines = line_equations(image)
    active = np.ones(n_sets, bool)
    for tolerance in tolerances:
        asked = valid & active[:, None]
        mi, ii, _ = nearest_lines(moved[asked], image, tolerance)
        sets, slots = (index[mi] for index in np.nonzero(asked))
        matched = np.zeros_like(asked)
        matched[sets, slots] = True
        line = np.zeros(asked.shape, int)
        line[sets, slots] = ii
        active &= matched.sum(axis=1) >= 3
        if not active.any():
            break
        x, y = moved[..., 0], moved[..., 1]  # (J, M, 2): both end points
        nx, ny, c = (np.broadcast_to(lines[line][..., k, None], x.shape) for k in range(3))
        weights = np.where(matched, segment_lengths(moved.reshape(-1, 2, 2)).reshape(matched.shape), 0.0)[..., None]
        rows = np.stack([nx * x + ny * y, -nx * y + ny * x, nx, ny], axis=-1) * weights[..., None]
        rhs = -c * weights
        solution = np.zeros((n_sets, 4))
        solution[active] = _least_squares(rows[active].reshape(-1, 2 * valid.shape[1], 4),
                                          rhs[active].reshape(-1, 2 * valid.shape[1]),
                                          np.repeat(matched[active], 2, axis=1))
        p, q, bx, by = solution.T
        active &= np.isfinite(solution).all(axis=1) & (np.hypot(p, q) >= 1e-6)
        step = np.where(active[:, None, None], np.stack([p, -q, bx, q, p, by], -1).reshape(-1, 2, 3), np.eye(2, 3))
        moved = moved.reshape(n_sets, -1, 2) @ step[:, :, :2].transpose(0, 2, 1)
        moved = _shifted(moved, step[:, :, 2]).reshape(model.shape)
        total = step[:, :, :2] @ total
        total[:, :, 2] += step[:, :, 2]
    return moved, total


def _least_squares(rows: np.ndarray, rhs: np.ndarray, used: np.ndarray) -> np.ndarray:
    """(J, 4): per set j, x minimising |rows[j] x - rhs[j]| over its ``used`` rows (the
    others are zero), as np.linalg.lstsq gives it, for all sets at once.

    By the 4x4 normal equations and one step of iterative refinement: within 1e-12 of
    lstsq on the ICP's systems (relative; 7e-11 without the refinement). Sets with a
    condition number above 1e3 (say, every end point matched to one line) lose digits
    that way and go to lstsq one by one, which also gives their minimum-norm answer.
    """
    rows_t = rows.transpose(0, 2, 1)
    gram = rows_t @ rows
    eigen = np.linalg.eigvalsh(gram)
    well = eigen[:, 0] > 1e-6 * eigen[:, -1]
    solution = np.empty((len(rows), 4))
    a, a_t, b, g = rows[well], rows_t[well], rhs[well][..., None], gram[well]
    x = np.linalg.solve(g, a_t @ b)
    solution[well] = (x + np.linalg.solve(g, a_t @ (b - a @ x)))[..., 0]
    for j in np.nonzero(~well)[0]:
        solution[j] = np.linalg.lstsq(rows[j, used[j]], rhs[j, used[j]], rcond=None)[0]
    return solution

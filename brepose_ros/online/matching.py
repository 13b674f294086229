"""The correspondence step: an image region's edge set against views' edge sets (seed
paper section 6).

For one image region and one view, both normalised for translation and scale
(``metric_space``), the distance matrix of their tetrads is solved as a bipartite
assignment with empty elements (Kuhn-Munkres, ``scipy.optimize.linear_sum_assignment``);
the matched pairs split into the nearest group and the rest. ``align`` chains the steps
and ranks the aligned views by coverage.

Where this goes beyond the paper, and why:

* In-plane rotation. The tetrad's two angles turn with the image, so the pair-wise
  matching is not rotation invariant, as the paper assumes: each job is a (view,
  rotation) pair that the pre-filter (``prefilter``) chose, and the assignment is solved
  with the view turned by that rotation.
* Distance. The tetrad (l, alpha, theta, r) is compared continuously: the midpoint as a
  point (|m| and alpha together), the perpendicular as its foot point (r and theta
  together), the orientation modulo 180 degrees, and the length. Raw angle differences
  jump by 2 pi at the wrap and are meaningless at the origin; these forms do not.
* Empty elements. Leaving a segment unmatched costs the empty distance e; a pair costs
  its distance. Clipping the matrix at 2e and dropping pairs at the clip is exactly the
  assignment with empty elements inserted on both sides, at the size of the real matrix.
* The matched pairs also give a similarity transform (Procrustes on the nearest pairs),
  which corrects the image normalisation that clutter and occlusion bias.
* Ranking. After that alignment, views are ranked by how much of the view's and of the
  region's edge length the other set covers (``coverage``, an F-measure), which picks the
  right view far more often than the assignment's distance sum (docs/DECISIONS.md).
* Batches. The jobs of one region run together: the views' segment sets are zero-padded
  to one size (``SegmentBatch``) and every step but Kuhn-Munkres, which runs per job on
  its real rows, is one array operation for all jobs, since per-call overhead dominated
  job by job. Distance matrices and assignments equal the job-by-job ones to the bit.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from ..metric_space import segment_lengths
from ..params import MatchParams
from .lines2d import line_equations, nearest_lines, point_segment_distance


@dataclass
class SegmentFeatures:
    """A normalised segment set in the forms the distance and the pre-filter need."""

    segments: np.ndarray  # (N, 2, 2) normalised
    lengths: np.ndarray  # (N,)
    midpoints: np.ndarray  # (N, 2)
    orientations: np.ndarray  # (N,) direction angle modulo pi
    feet: np.ndarray  # (N, 2) foot of the perpendicular from the origin to the line


def longest(segments: np.ndarray, count: int) -> np.ndarray:
    """Indices of the ``count`` longest segments (all if fewer), longest first."""
    order = np.argsort(-segment_lengths(segments), kind="stable")
    return order[:count]


def describe(segments: np.ndarray) -> SegmentFeatures:
    """Features of a normalised segment set (N, 2, 2)."""
    segments = np.asarray(segments, dtype=float)
    return SegmentFeatures(segments, *_geometry(segments))


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


def coverage(model: np.ndarray, valid: np.ndarray, image: np.ndarray, tolerance: float,
             max_angle_deg: float = 12.0, per_segment: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Two-way edge coverage of each model set (J, M, 2, 2; ``valid`` marks real segments)
    and the image segments: the share of the set's length, and the share of the image's,
    lying within ``tolerance`` of a parallel segment of the other side. An oriented chamfer
    test in the normalised frame, on ``per_segment`` points per segment (a quarter of a
    segment is resolution enough to rank views). Parallel means within ``max_angle_deg``,
    a little wider than the line association's 10 degrees: the aligned view is still a
    view up to half the graph's spacing away from the true one.

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


@dataclass
class Alignment:
    """What ``align`` found for the jobs of a batch whose pairs gave a similarity."""

    jobs: np.ndarray  # (K,) indices into the batch
    scale: np.ndarray  # (K,) the similarity normalised model -> normalised image, after 2D ICP
    angle: np.ndarray  # (K,)
    shift: np.ndarray  # (K, 2)
    coverage: np.ndarray  # (K,) F-measure of the two-way edge coverage after alignment


def align(model: SegmentBatch, image: SegmentFeatures, phi: np.ndarray, p: MatchParams) -> Alignment:
    """The correspondence step for a batch of jobs (model sets turned by ``phi``) against
    one image region: Kuhn-Munkres at each rotation, the similarity its nearest pairs
    imply, a second assignment with that similarity applied (kept where it costs less),
    then the similarity polished by 2D ICP against the region's lines and the aligned
    sets ranked by ``coverage``. Jobs whose pairs give no similarity drop out."""
    best = assign(model, image, phi, p)
    similarity = similarity_from_pairs(model, image, best, phi)
    jobs = np.nonzero(similarity.found)[0]
    if len(jobs) == 0:
        return Alignment(jobs, np.zeros(0), np.zeros(0), np.zeros((0, 2)), np.zeros(0))
    model, best, similarity = take(model, jobs), take(best, jobs), take(similarity, jobs)
    # re-match with the similarity applied: the pairs now say what is really aligned
    moved = apply_similarity(model.segments, similarity.scale, similarity.angle, similarity.shift)
    refined = assign(SegmentBatch.of(moved, model.valid), image, np.zeros(len(jobs)), p)
    better = similarity_from_pairs(model, image, refined, similarity.angle)
    switch = (refined.cost < best.cost) & better.found
    for name in ("scale", "angle", "shift"):
        getattr(similarity, name)[switch] = getattr(better, name)[switch]
    a, angle, b = similarity.scale, similarity.angle, similarity.shift
    moved = apply_similarity(model.segments, a, angle, b)
    tolerance = p.coverage_tolerance
    # a wide ICP round brings similarities off by more than the tolerance within reach
    moved, polish = align_to_lines(moved, model.valid, image.segments, (3 * tolerance, tolerance))
    A = polish[:, :, :2] @ (a[:, None, None] * rotations(angle))
    b = np.einsum("jkl,jl->jk", polish[:, :, :2], b) + polish[:, :, 2]
    a, angle = np.sqrt(np.abs(np.linalg.det(A))), np.arctan2(A[:, 1, 0], A[:, 0, 0])
    covered_model, covered_image = coverage(moved, model.valid, image.segments, tolerance)
    f_measure = 2 * covered_model * covered_image / np.maximum(covered_model + covered_image, 1e-12)
    return Alignment(jobs, a, angle, b, f_measure)

"""The correspondence step: an image region's edge set against views' edge sets (seed
paper section 6).

For one image region and one view, both normalised for translation and scale
(``metric_space``), the distance matrix of their tetrads is solved as a bipartite
assignment with empty elements (Kuhn-Munkres, ``_assignment``); the matched pairs split
into the nearest group and the rest. ``align`` chains the steps and ranks the aligned
views by coverage.

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
  region's edge length the other set covers (``_coverage``, an F-measure), which picks
  the right view far more often than the assignment's distance sum (docs/DECISIONS.md).
* Compiled. A worker's chunk of jobs runs as one numba ``nogil`` call (``align_kernel``):
  as numpy, each job was dozens of short array calls and a SciPy Kuhn-Munkres call, each
  taking and releasing the GIL, and two threads spent their time handing it over
  (docs/results/latency.md). The Kuhn-Munkres is SciPy's algorithm step for step
  (shortest augmenting paths, Crouse 2016), so it picks the same pairs, ties included.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..metric_space import segment_lengths
from ..params import MatchParams
from .kernels import nearest_lines_kernel
from .lines2d import NEAREST_MAX_ANGLE_DEG, cos_deg

#: coverage counts segments within this angle as parallel, a little wider than the line
#: association's 10 degrees: the aligned view is still a view up to half the graph's
#: spacing away from the true one
COVERAGE_MAX_ANGLE_DEG = 12.0
#: points per segment tested by the coverage: a quarter of a segment is resolution enough
#: to rank views
COVERAGE_POINTS = 4


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
    segments = np.ascontiguousarray(segments, dtype=float).reshape(-1, 2, 2)
    return SegmentFeatures(segments, *_geometry(segments))


def rotations(angle: np.ndarray) -> np.ndarray:
    """(J, 2, 2) rotation matrices [[c, -s], [s, c]]."""
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c, -s, s, c], axis=-1).reshape(np.shape(angle) + (2, 2))


@dataclass
class Alignment:
    """What ``align`` found for the jobs of a batch whose pairs gave a similarity."""

    jobs: np.ndarray  # (K,) indices into the batch
    scale: np.ndarray  # (K,) the similarity normalised model -> normalised image, after 2D ICP
    angle: np.ndarray  # (K,)
    shift: np.ndarray  # (K, 2)
    coverage: np.ndarray  # (K,) F-measure of the two-way edge coverage after alignment


def align(segments: np.ndarray, offsets: np.ndarray, views: np.ndarray, phi: np.ndarray, region_segments: np.ndarray,
          region_offsets: np.ndarray, regions: np.ndarray, p: MatchParams) -> Alignment:
    """The correspondence step for a batch of jobs: job j is view ``views[j]`` (segments
    ``segments[offsets[v]:offsets[v + 1]]``, normalised) turned by ``phi[j]`` against image
    region ``regions[j]`` (segments ``region_segments[region_offsets[r]:region_offsets[r + 1]]``,
    normalised). Kuhn-Munkres at that rotation, the similarity its nearest pairs imply, a
    second assignment with that similarity applied (kept where it costs less), then the
    similarity polished by 2D ICP against the region's lines and the aligned sets ranked by
    coverage. Jobs whose pairs give no similarity drop out. One compiled call, the GIL
    released throughout (``align_kernel``), whatever regions the jobs are of: a seed of the
    search is a region with one job, and one call per seed cost more than its matching."""
    found, out = np.zeros(len(views), np.bool_), np.zeros((len(views), 5))
    weights = np.array([p.weight_length, p.weight_midpoint, p.weight_orientation, p.weight_perpendicular])
    # contiguous, as the kernel was warmed with (a dealt chunk of jobs is strided)
    align_kernel(segments, offsets, np.ascontiguousarray(views, np.int64), np.ascontiguousarray(phi, float),
                 region_segments, region_offsets, np.ascontiguousarray(regions, np.int64), weights,
                 p.empty_coefficient, p.nearest_threshold, p.coverage_tolerance, cos_deg(NEAREST_MAX_ANGLE_DEG),
                 cos_deg(COVERAGE_MAX_ANGLE_DEG), found, out)
    jobs = np.nonzero(found)[0]
    return Alignment(jobs, out[jobs, 0], out[jobs, 1], out[jobs, 2:4], out[jobs, 4])


@njit(nogil=True, cache=True)
def align_kernel(segments: np.ndarray, offsets: np.ndarray, views: np.ndarray, phi: np.ndarray,
                 region_segments: np.ndarray, region_offsets: np.ndarray, regions: np.ndarray, weights: np.ndarray,
                 empty_coefficient: float, nearest_threshold: float, tolerance: float, line_cos: float,
                 coverage_cos: float, found: np.ndarray, out: np.ndarray) -> None:
    """``align`` for every job: found[j] whether job j gave a similarity, out[j] its
    (scale, angle, shift x, shift y, coverage F-measure)."""
    region = -1
    image = region_segments[:0]
    i_geometry = _geometry(image)
    for j in range(len(views)):
        if regions[j] != region:  # a region's jobs come together: its geometry once for them
            region = regions[j]
            image = region_segments[region_offsets[region]:region_offsets[region + 1]]
            i_geometry = _geometry(image)
        i_lengths = i_geometry[0]
        model = segments[offsets[views[j]]:offsets[views[j] + 1]]
        m_geometry = _geometry(model)
        cost, index, nearest = _assignment(m_geometry, i_geometry, phi[j], weights, empty_coefficient,
                                           nearest_threshold)
        scale, angle, shift, ok = _similarity_from_pairs(model, m_geometry[0], image, i_lengths, index, nearest,
                                                         phi[j])
        if not ok:
            continue
        found[j] = True
        # re-match with the similarity applied: the pairs now say what is really aligned
        moved = _apply_similarity(model, scale, angle, shift)
        moved_cost, index, nearest = _assignment(_geometry(moved), i_geometry, 0.0, weights, empty_coefficient,
                                                 nearest_threshold)
        better = _similarity_from_pairs(model, m_geometry[0], image, i_lengths, index, nearest, angle)
        if moved_cost < cost and better[3]:
            scale, angle, shift = better[0], better[1], better[2]
        moved = _apply_similarity(model, scale, angle, shift)
        # a wide ICP round brings similarities off by more than the tolerance within reach
        polish = _align_to_lines(moved, image, np.array([3.0 * tolerance, tolerance]), line_cos)
        # the polish composed onto the similarity: A = polish[:, :2] scale R(angle)
        sc, ss = scale * math.cos(angle), scale * math.sin(angle)
        a00, a01 = polish[0, 0] * sc + polish[0, 1] * ss, polish[0, 0] * -ss + polish[0, 1] * sc
        a10, a11 = polish[1, 0] * sc + polish[1, 1] * ss, polish[1, 0] * -ss + polish[1, 1] * sc
        out[j, 0] = math.sqrt(abs(a00 * a11 - a01 * a10))
        out[j, 1] = math.atan2(a10, a00)
        out[j, 2] = polish[0, 0] * shift[0] + polish[0, 1] * shift[1] + polish[0, 2]
        out[j, 3] = polish[1, 0] * shift[0] + polish[1, 1] * shift[1] + polish[1, 2]
        covered_model, covered_image = _coverage(moved, image, tolerance, coverage_cos)
        out[j, 4] = 2 * covered_model * covered_image / max(covered_model + covered_image, 1e-12)


@njit(nogil=True, cache=True)
def _geometry(segments: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lengths, midpoints, orientations modulo pi and perpendicular feet of segments (N, 2, 2)."""
    n = len(segments)
    lengths, midpoints, orientations, feet = np.empty(n), np.empty((n, 2)), np.empty(n), np.empty((n, 2))
    for i in range(n):
        ax, ay, bx, by = segments[i, 0, 0], segments[i, 0, 1], segments[i, 1, 0], segments[i, 1, 1]
        dx, dy = bx - ax, by - ay
        lengths[i] = math.sqrt(dx * dx + dy * dy)
        mx, my = (ax + bx) / 2.0, (ay + by) / 2.0
        midpoints[i, 0], midpoints[i, 1] = mx, my
        orientations[i] = _mod(math.atan2(dy, dx), math.pi)
        ux, uy = dx / max(lengths[i], 1e-12), dy / max(lengths[i], 1e-12)
        along = mx * ux + my * uy
        feet[i, 0], feet[i, 1] = mx - along * ux, my - along * uy
    return lengths, midpoints, orientations, feet


@njit(nogil=True, cache=True)
def _mod(x: float, period: float) -> float:
    """np.mod(x, period) for a positive period, to the bit (fmod, then the sign of the period).
    Within one period either side of [0, period) fmod is x itself or x - period, which is
    exact there (Sterbenz): the tetrad distances' wraps, too many for fmod's cost."""
    if -period < x < period:
        rest = x
    elif period <= x < 2.0 * period:
        rest = x - period
    else:
        rest = np.fmod(x, period)
    if rest < 0.0:
        return rest + period
    return rest if rest != 0.0 else 0.0


@njit(nogil=True, cache=True)
def _distances(model, image, phi: float, weights: np.ndarray) -> np.ndarray:
    """(M, N) tetrad distances of the model's segments turned by ``phi`` to the image's;
    both as ``_geometry`` gives them."""
    m_lengths, m_mid, m_orient, m_feet = model
    i_lengths, i_mid, i_orient, i_feet = image
    c, s = math.cos(phi), math.sin(phi)
    dist = np.empty((len(m_lengths), len(i_lengths)))
    for r in range(len(m_lengths)):
        mx, my = m_mid[r, 0] * c - m_mid[r, 1] * s, m_mid[r, 0] * s + m_mid[r, 1] * c
        fx, fy = m_feet[r, 0] * c - m_feet[r, 1] * s, m_feet[r, 0] * s + m_feet[r, 1] * c
        for k in range(len(i_lengths)):
            d_length = m_lengths[r] - i_lengths[k]
            squared = weights[0] * (d_length * d_length)
            dx, dy = mx - i_mid[k, 0], my - i_mid[k, 1]
            squared += weights[1] * (dx * dx + dy * dy)
            # orientations are directions modulo pi: their difference wraps to [-pi/2, pi/2)
            d_orient = _mod(m_orient[r] + phi - i_orient[k] + math.pi / 2, math.pi) - math.pi / 2
            squared += weights[2] * (d_orient * d_orient)
            dx, dy = fx - i_feet[k, 0], fy - i_feet[k, 1]
            squared += weights[3] * (dx * dx + dy * dy)
            dist[r, k] = math.sqrt(squared)
    return dist


@njit(nogil=True, cache=True)
def _assignment(model, image, phi: float, weights: np.ndarray, empty_coefficient: float,
                nearest_threshold: float) -> tuple[float, np.ndarray, np.ndarray]:
    """Bipartite matching with empty elements on both sides of the model (turned by ``phi``)
    and the image: its cost (the distance sum with empty elements, per element of both
    sets), the image segment paired with each model segment (-1 if empty) and whether the
    pair is in the nearest group.

    As in the paper, the empty distance is tied to the largest distance of the matrix
    (``empty_coefficient`` times it); pairs in the nearest group are closer than
    ``nearest_threshold`` times the empty distance.
    """
    dist = _distances(model, image, phi, weights)
    n_model, n_image = dist.shape
    empty = empty_coefficient * max(dist.max(), 0.0) if dist.size else 0.0
    clip = 2.0 * empty
    index = _kuhn_munkres(np.minimum(dist, clip))
    nearest = np.zeros(n_model, np.bool_)
    n_pairs, total = 0, 0.0
    for r in range(n_model):
        k = index[r]
        if k >= 0 and dist[r, k] < clip:
            n_pairs += 1
            total += dist[r, k]
            nearest[r] = dist[r, k] < nearest_threshold * empty
        else:
            index[r] = -1
    unmatched = (n_model - n_pairs) + (n_image - n_pairs)
    return (total + empty * unmatched) / (n_model + n_image), index, nearest


@njit(nogil=True, cache=True)
def _kuhn_munkres(cost: np.ndarray) -> np.ndarray:
    """The column assigned to each row of ``cost`` (-1 if none) minimising the sum:
    ``scipy.optimize.linear_sum_assignment``'s algorithm (shortest augmenting paths,
    Crouse 2016, scipy's rectangular_lsap.cpp) step for step, so the same pairs, ties
    included. A tall matrix is solved transposed, as there."""
    n_rows, n_cols = cost.shape
    transpose = n_cols < n_rows
    if transpose:
        cost = cost.T.copy()
        n_rows, n_cols = n_cols, n_rows
    u, v = np.zeros(n_rows), np.zeros(n_cols)
    path, col4row, row4col = np.full(n_cols, -1), np.full(n_rows, -1), np.full(n_cols, -1)
    shortest = np.empty(n_cols)
    in_rows, in_cols = np.zeros(n_rows, np.bool_), np.zeros(n_cols, np.bool_)
    remaining = np.empty(n_cols, np.int64)
    for current in range(n_rows):
        # Dijkstra from the current row over reduced costs to the nearest free column
        for it in range(n_cols):
            remaining[it] = n_cols - it - 1  # in reverse, as scipy: a constant matrix gives the identity
        n_remaining = n_cols
        in_rows[:] = False
        in_cols[:] = False
        shortest[:] = np.inf
        min_value, i, sink = 0.0, current, -1
        while sink == -1:
            index, lowest = -1, np.inf
            in_rows[i] = True
            for it in range(n_remaining):
                j = remaining[it]
                reduced = min_value + cost[i, j] - u[i] - v[j]
                if reduced < shortest[j]:
                    path[j], shortest[j] = i, reduced
                # among equal costs prefer a free column: it ends the path
                if shortest[j] < lowest or (shortest[j] == lowest and row4col[j] == -1):
                    lowest, index = shortest[j], it
            min_value = lowest
            j = remaining[index]
            if row4col[j] == -1:
                sink = j
            else:
                i = row4col[j]
            in_cols[j] = True
            n_remaining -= 1
            remaining[index] = remaining[n_remaining]
        # the dual variables, then the matching along the path
        u[current] += min_value
        for i in range(n_rows):
            if in_rows[i] and i != current:
                u[i] += min_value - shortest[col4row[i]]
        for j in range(n_cols):
            if in_cols[j]:
                v[j] -= min_value - shortest[j]
        j = sink
        while True:
            i = path[j]
            row4col[j] = i
            col4row[i], j = j, col4row[i]
            if i == current:
                break
    if not transpose:
        return col4row
    col_of_row = np.full(n_cols, -1)
    for row in range(n_rows):
        col_of_row[col4row[row]] = row
    return col_of_row


@njit(nogil=True, cache=True)
def _similarity_from_pairs(model: np.ndarray, m_lengths: np.ndarray, image: np.ndarray, i_lengths: np.ndarray,
                           index: np.ndarray, nearest: np.ndarray, phi: float) -> tuple[float, float, np.ndarray, bool]:
    """(scale, angle, shift, found): the similarity mapping the model onto the image from the
    nearest pairs, not found with fewer than two.

    Weighted 2D Procrustes (Umeyama) over the pairs' end points, each pair weighted by its
    shorter segment and its end points taken in the order that fits best once the model
    is turned by ``phi``, the rotation the pairs were matched at.
    """
    c, s = math.cos(phi), math.sin(phi)
    src, dst, w = np.zeros((2 * len(model), 2)), np.zeros((2 * len(model), 2)), np.zeros(2 * len(model))
    for r in range(len(model)):
        if not nearest[r]:
            continue
        k = index[r]
        straight = swapped = 0.0
        for e in range(2):
            x, y = model[r, e, 0], model[r, e, 1]
            tx, ty = x * c - y * s, x * s + y * c
            straight += (tx - image[k, e, 0]) ** 2 + (ty - image[k, e, 1]) ** 2
            swapped += (tx - image[k, 1 - e, 0]) ** 2 + (ty - image[k, 1 - e, 1]) ** 2
        for e in range(2):
            src[2 * r + e] = model[r, e]
            dst[2 * r + e] = image[k, 1 - e] if swapped < straight else image[k, e]
            w[2 * r + e] = min(m_lengths[r], i_lengths[k])
    scale, angle, shift, found = _weighted_similarity(src, dst, w)
    return scale, angle, shift, found and nearest.sum() >= 2


@njit(nogil=True, cache=True)
def _weighted_similarity(src: np.ndarray, dst: np.ndarray,
                         weights: np.ndarray) -> tuple[float, float, np.ndarray, bool]:
    """(scale, angle, shift, found) minimising sum w |scale R(angle) src + shift - dst|^2 over
    points (P, 2); not found where the source points do not spread or the scale is not
    positive."""
    w = weights / max(weights.sum(), 1e-12)
    mu_s, mu_d = np.zeros(2), np.zeros(2)
    for i in range(len(w)):
        mu_s += w[i] * src[i]
        mu_d += w[i] * dst[i]
    var, cross = 0.0, np.zeros((2, 2))
    for i in range(len(w)):
        ax, ay, bx, by = src[i, 0] - mu_s[0], src[i, 1] - mu_s[1], dst[i, 0] - mu_d[0], dst[i, 1] - mu_d[1]
        var += w[i] * (ax * ax + ay * ay)
        cross[0, 0] += w[i] * ax * bx
        cross[0, 1] += w[i] * ax * by
        cross[1, 0] += w[i] * ay * bx
        cross[1, 1] += w[i] * ay * by
    angle = math.atan2(cross[0, 1] - cross[1, 0], cross[0, 0] + cross[1, 1])
    c, s = math.cos(angle), math.sin(angle)
    spread = var > 1e-12
    # sum w (R a) . b is the trace of R^T times the weighted cross covariance
    scale = (c * (cross[0, 0] + cross[1, 1]) + s * (cross[0, 1] - cross[1, 0])) / (var if spread else 1.0)
    shift = np.array([mu_d[0] - scale * (c * mu_s[0] - s * mu_s[1]), mu_d[1] - scale * (s * mu_s[0] + c * mu_s[1])])
    return scale, angle, shift, spread and scale > 0


@njit(nogil=True, cache=True)
def _apply_similarity(segments: np.ndarray, scale: float, angle: float, shift: np.ndarray) -> np.ndarray:
    """Segments (N, 2, 2) mapped by scale R(angle) x + shift."""
    c, s = math.cos(angle), math.sin(angle)
    moved = np.empty_like(segments)
    for i in range(len(segments)):
        for e in range(2):
            x, y = scale * segments[i, e, 0], scale * segments[i, e, 1]
            moved[i, e, 0], moved[i, e, 1] = x * c - y * s + shift[0], x * s + y * c + shift[1]
    return moved


@njit(nogil=True, cache=True)
def _align_to_lines(moved: np.ndarray, image: np.ndarray, tolerances: np.ndarray, line_cos: float) -> np.ndarray:
    """2D ICP on segments: a similarity pulling the end points of ``moved`` (N, 2, 2, moved
    in place) onto their nearest image lines, re-associating at each tolerance in turn
    (normalised units). Returns the (2, 3) similarity matrix applied.

    The similarity x' = [[p, -q], [q, p]] x + b is linear in (p, q, bx, by), and so is the
    distance of x' to a line: each round is one 4-unknown least-squares solve. It stops
    when fewer than three segments find a line or the solve degenerates.
    """
    total = np.zeros((2, 3))
    total[0, 0] = total[1, 1] = 1.0
    lines = _line_equations(image)
    best, best_cost = np.empty(len(moved), np.int64), np.empty(len(moved))
    for tolerance in tolerances:
        nearest_lines_kernel(moved, image, tolerance, line_cos, best, best_cost)
        matched = np.nonzero(best >= 0)[0]
        if len(matched) < 3:
            break
        rows, rhs = np.empty((2 * len(matched), 4)), np.empty(2 * len(matched))
        for m in range(len(matched)):
            r = matched[m]
            nx, ny, offset = lines[best[r], 0], lines[best[r], 1], lines[best[r], 2]
            dx, dy = moved[r, 1, 0] - moved[r, 0, 0], moved[r, 1, 1] - moved[r, 0, 1]
            weight = math.sqrt(dx * dx + dy * dy)  # long segments are the reliable ones
            for e in range(2):
                x, y = moved[r, e, 0], moved[r, e, 1]
                rows[2 * m + e, 0], rows[2 * m + e, 1] = (nx * x + ny * y) * weight, (-nx * y + ny * x) * weight
                rows[2 * m + e, 2], rows[2 * m + e, 3] = nx * weight, ny * weight
                rhs[2 * m + e] = -offset * weight
        p, q, bx, by = _least_squares(rows, rhs)
        if not (np.isfinite(p) and np.isfinite(q) and np.isfinite(bx) and np.isfinite(by) and math.hypot(p, q) >= 1e-6):
            break
        for i in range(len(moved)):
            for e in range(2):
                x, y = moved[i, e, 0], moved[i, e, 1]
                moved[i, e, 0], moved[i, e, 1] = x * p - y * q + bx, x * q + y * p + by
        t0, t1 = total[0].copy(), total[1].copy()
        total[0] = p * t0 - q * t1
        total[1] = q * t0 + p * t1
        total[0, 2] += bx
        total[1, 2] += by
    return total


@njit(nogil=True, cache=True)
def _line_equations(segments: np.ndarray) -> np.ndarray:
    """(K, 3) lines a x + b y + c = 0 of segments (K, 2, 2), (a, b) a unit normal."""
    lines = np.empty((len(segments), 3))
    for k in range(len(segments)):
        x, y = segments[k, 0, 0], segments[k, 0, 1]
        dx, dy = segments[k, 1, 0] - x, segments[k, 1, 1] - y
        length = max(math.sqrt(dx * dx + dy * dy), 1e-12)
        lines[k, 0], lines[k, 1] = -dy / length, dx / length
        lines[k, 2] = -(lines[k, 0] * x + lines[k, 1] * y)
    return lines


@njit(nogil=True, cache=True)
def _least_squares(rows: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """x minimising |rows x - rhs| (minimum norm where that is not unique), as
    np.linalg.lstsq gives it: by one-sided Jacobi SVD (Hestenes), accurate also where every
    end point lies on one line and the normal equations lose their digits."""
    n = rows.shape[1]
    u, v = rows.copy(), np.eye(n)
    for _ in range(60):
        turned = False
        for a in range(n - 1):
            for b in range(a + 1, n):
                alpha, beta, gamma = 0.0, 0.0, 0.0
                for i in range(len(u)):
                    alpha += u[i, a] * u[i, a]
                    beta += u[i, b] * u[i, b]
                    gamma += u[i, a] * u[i, b]
                if abs(gamma) <= 1e-15 * math.sqrt(alpha * beta):
                    continue
                turned = True
                # the plane rotation that makes columns a and b orthogonal
                zeta = (beta - alpha) / (2.0 * gamma)
                t = math.copysign(1.0, zeta) / (abs(zeta) + math.sqrt(1.0 + zeta * zeta))
                c = 1.0 / math.sqrt(1.0 + t * t)
                s = c * t
                for m in (u, v):
                    for i in range(len(m)):
                        ma, mb = m[i, a], m[i, b]
                        m[i, a], m[i, b] = c * ma - s * mb, s * ma + c * mb
        if not turned:
            break
    sigma = np.sqrt((u * u).sum(axis=0))
    # lstsq's default cut-off: singular values below eps max(M, N) times the largest are zero
    cutoff = 2.220446049250313e-16 * max(len(rows), n) * sigma.max()
    x = np.zeros(n)
    for k in range(n):
        if sigma[k] > cutoff:
            along = 0.0
            for i in range(len(u)):
                along += u[i, k] * rhs[i]
            x += along / (sigma[k] * sigma[k]) * v[:, k]
    return x


@njit(nogil=True, cache=True)
def _coverage(model: np.ndarray, image: np.ndarray, tolerance: float, min_cos: float) -> tuple[float, float]:
    """Two-way edge coverage of the model's segments and the image's: the share of the
    model's length, and the share of the image's, lying within ``tolerance`` of a parallel
    segment of the other side (within ``min_cos``), tested on ``COVERAGE_POINTS`` points per
    segment: an oriented chamfer test in the normalised frame.

    Only parallel pairs whose bounding boxes lie closer than the tolerance (plus a margin
    far above rounding) can cover; the points are measured for those pairs only.
    """
    n_points = COVERAGE_POINTS
    covered_model = np.zeros((len(model), n_points), np.bool_)
    covered_image = np.zeros((len(image), n_points), np.bool_)
    m_lengths, i_lengths = _geometry(model)[0], _geometry(image)[0]
    for f in range(len(model)):
        fx, fy = model[f, 1, 0] - model[f, 0, 0], model[f, 1, 1] - model[f, 0, 1]
        for k in range(len(image)):
            ix, iy = image[k, 1, 0] - image[k, 0, 0], image[k, 1, 1] - image[k, 0, 1]
            if not abs(fx * ix + fy * iy) / max(m_lengths[f] * i_lengths[k], 1e-18) > min_cos:
                continue
            gap = -np.inf
            for axis in range(2):
                f_lo, f_hi = min(model[f, 0, axis], model[f, 1, axis]), max(model[f, 0, axis], model[f, 1, axis])
                i_lo, i_hi = min(image[k, 0, axis], image[k, 1, axis]), max(image[k, 0, axis], image[k, 1, axis])
                gap = max(gap, f_lo - i_hi, i_lo - f_hi)
            if not gap < tolerance * (1 + 1e-6):
                continue
            for point in range(n_points):
                frac = (point + 0.5) / n_points
                if _point_distance(model[f], frac, image[k]) < tolerance:
                    covered_model[f, point] = True
                if _point_distance(image[k], frac, model[f]) < tolerance:
                    covered_image[k, point] = True
    model_share = (covered_model.sum(axis=1) * (m_lengths / n_points)).sum() / max(m_lengths.sum(), 1e-18)
    image_share = (covered_image.sum(axis=1) * (i_lengths / n_points)).sum() / max(i_lengths.sum(), 1e-18)
    return model_share, image_share


@njit(nogil=True, cache=True)
def _point_distance(source: np.ndarray, frac: float, target: np.ndarray) -> float:
    """Distance of the point at ``frac`` along segment ``source`` (2, 2) to segment ``target``."""
    px = source[0, 0] + frac * (source[1, 0] - source[0, 0])
    py = source[0, 1] + frac * (source[1, 1] - source[0, 1])
    ax, ay = target[0, 0], target[0, 1]
    dx, dy = target[1, 0] - ax, target[1, 1] - ay
    u = min(max(((px - ax) * dx + (py - ay) * dy) / max(dx * dx + dy * dy, 1e-18), 0.0), 1.0)
    ex, ey = px - (ax + u * dx), py - (ay + u * dy)
    return math.sqrt(ex * ex + ey * ey)

"""Compiled kernels of the online path: loops that numpy can only run as many small calls,
each holding the GIL, written once as plain loops and compiled by numba with ``nogil`` so
that the worker threads (``workers``) really run them side by side.

``cache=True`` keeps the machine code beside this file (``__pycache__``), so a process
compiles a kernel only once per installation; ``warm_up`` runs each kernel on a tiny input
so that even that first compilation, or the cache load, happens when the estimator is built,
not on the first image (docs/DECISIONS.md, threads).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..params import MatchParams


@njit(nogil=True, cache=True)
def _rodrigues(w: np.ndarray) -> np.ndarray:
    """Rotation matrix exp([w]x) of a rotation vector (OpenCV's Rodrigues formula)."""
    theta = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    out = np.eye(3)
    if theta < 2.220446049250313e-16:
        return out
    c, s = math.cos(theta), math.sin(theta)
    c1 = 1.0 - c
    x, y, z = w[0] / theta, w[1] / theta, w[2] / theta
    out[0, 0], out[0, 1], out[0, 2] = c + c1 * x * x, c1 * x * y - s * z, c1 * x * z + s * y
    out[1, 0], out[1, 1], out[1, 2] = c1 * x * y + s * z, c + c1 * y * y, c1 * y * z - s * x
    out[2, 0], out[2, 1], out[2, 2] = c1 * x * z - s * y, c1 * y * z + s * x, c + c1 * z * z
    return out


@njit(nogil=True, cache=True)
def _cholesky_solve(a: np.ndarray, b: np.ndarray, x: np.ndarray) -> bool:
    """x = a^-1 b for a symmetric positive definite 6x6 (or n x n) a; False if it is not."""
    n = a.shape[0]
    low = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            total = a[i, j]
            for k in range(j):
                total -= low[i, k] * low[j, k]
            if i == j:
                if not total > 0.0:
                    return False
                low[i, i] = math.sqrt(total)
            else:
                low[i, j] = total / low[j, j]
    y = np.empty(n)
    for i in range(n):
        total = b[i]
        for k in range(i):
            total -= low[i, k] * y[k]
        y[i] = total / low[i, i]
    for i in range(n - 1, -1, -1):
        total = y[i]
        for k in range(i + 1, n):
            total -= low[k, i] * x[k]
        x[i] = total / low[i, i]
    return True


@njit(nogil=True, cache=True)
def refine_poses_kernel(R: np.ndarray, t: np.ndarray, points: np.ndarray, lines: np.ndarray, per_pair: int,
                        weights: np.ndarray, ends: np.ndarray, active: np.ndarray, f_scale: np.ndarray,
                        iterations: int, normal_out: np.ndarray, variance_out: np.ndarray) -> None:
    """``refinement.refine_poses`` on prepared arrays, R (B, 3, 3) and t (B, 3) in place.

    points (N, 3) model points, ``per_pair`` consecutive ones per image line of lines
    (K, 3) with weights (K,); pose b owns the points ``ends[b]:ends[b + 1]``, refines if
    ``active[b]`` with Huber threshold ``f_scale[b]``. Each pose runs its own loop of the
    same Gauss-Newton steps as the batched numpy version had (the sums run in another
    order: the last bits may differ).
    normal_out (B, 6, 6) and variance_out (B,) receive each pose's last undamped normal
    matrix J^T W J and weighted residual variance (left as they are for a pose that took
    no step), from which the caller forms the covariance.
    """
    for b in range(len(R)):
        if active[b]:
            _gauss_newton(R[b], t[b], points, lines, per_pair, weights, ends[b], ends[b + 1], f_scale[b], iterations,
                          normal_out[b], variance_out[b:b + 1])


@njit(nogil=True, cache=True)
def _gauss_newton(R: np.ndarray, t: np.ndarray, points: np.ndarray, lines: np.ndarray, per_pair: int,
                  weights: np.ndarray, lo: int, hi: int, f_scale: float, iterations: int, normal_out: np.ndarray,
                  variance_out: np.ndarray) -> None:
    """``refine_poses_kernel`` for one pose R (3, 3), t (3,) (in place) on the points lo:hi;
    normal_out (6, 6), variance_out (1,). The normal matrix's lower triangle and the gradient
    are summed in locals, each in the same order as into the arrays: the same bits, while
    array elements were loaded and stored at every point (the edge alignment 5 % faster)."""
    hessian = np.empty((6, 6))
    gradient = np.empty(6)
    step = np.empty(6)
    turned = np.empty((3, 3))
    for _ in range(iterations):
        h00 = h10 = h11 = h20 = h21 = h22 = h30 = h31 = h32 = h33 = 0.0
        h40 = h41 = h42 = h43 = h44 = h50 = h51 = h52 = h53 = h54 = h55 = 0.0
        b0 = b1 = b2 = b3 = b4 = b5 = 0.0
        weighted_squares = 0.0
        for n in range(lo, hi):
            px, py, pz = points[n, 0], points[n, 1], points[n, 2]
            r0 = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz
            r1 = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz
            r2 = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz
            x, y, z = r0 + t[0], r1 + t[1], max(r2 + t[2], 1e-9)
            k = n // per_pair
            nx, ny = lines[k, 0], lines[k, 1]
            along = nx * (x / z) + ny * (y / z)
            residual = along + lines[k, 2]
            # d residual / d X_cam = g, chained through X_cam = exp(w) R X + t
            g0, g1, g2 = nx / z, ny / z, -along / z
            j0, j1, j2 = r1 * g2 - r2 * g1, r2 * g0 - r0 * g2, r0 * g1 - r1 * g0
            j3, j4, j5 = g0, g1, g2
            weight = f_scale / max(abs(residual), f_scale) * weights[k]  # Huber
            weighted_squares += weight * residual * residual
            w0, w1, w2, w3, w4, w5 = weight * j0, weight * j1, weight * j2, weight * j3, weight * j4, weight * j5
            b0 -= w0 * residual
            b1 -= w1 * residual
            b2 -= w2 * residual
            b3 -= w3 * residual
            b4 -= w4 * residual
            b5 -= w5 * residual
            h00 += w0 * j0
            h10 += w1 * j0
            h11 += w1 * j1
            h20 += w2 * j0
            h21 += w2 * j1
            h22 += w2 * j2
            h30 += w3 * j0
            h31 += w3 * j1
            h32 += w3 * j2
            h33 += w3 * j3
            h40 += w4 * j0
            h41 += w4 * j1
            h42 += w4 * j2
            h43 += w4 * j3
            h44 += w4 * j4
            h50 += w5 * j0
            h51 += w5 * j1
            h52 += w5 * j2
            h53 += w5 * j3
            h54 += w5 * j4
            h55 += w5 * j5
        gradient[0], gradient[1], gradient[2], gradient[3], gradient[4], gradient[5] = b0, b1, b2, b3, b4, b5
        hessian[0, 0] = h00
        hessian[1, 0], hessian[1, 1] = h10, h11
        hessian[2, 0], hessian[2, 1], hessian[2, 2] = h20, h21, h22
        hessian[3, 0], hessian[3, 1], hessian[3, 2], hessian[3, 3] = h30, h31, h32, h33
        hessian[4, 0], hessian[4, 1], hessian[4, 2], hessian[4, 3], hessian[4, 4] = h40, h41, h42, h43, h44
        hessian[5, 0], hessian[5, 1], hessian[5, 2], hessian[5, 3], hessian[5, 4], hessian[5, 5] = \
            h50, h51, h52, h53, h54, h55
        for i in range(6):
            for j in range(i):
                hessian[j, i] = hessian[i, j]
        if hi - lo > 6:
            normal_out[:] = hessian
            variance_out[0] = weighted_squares / (hi - lo - 6)
        damping = 1e-6 * (hessian[0, 0] + hessian[1, 1] + hessian[2, 2] + hessian[3, 3] + hessian[4, 4]
                          + hessian[5, 5]) / 6.0  # degenerate line sets
        for i in range(6):
            hessian[i, i] += damping
        if not _cholesky_solve(hessian, gradient, step):
            break
        finite = True
        for i in range(6):
            finite = finite and math.isfinite(step[i])
        if not finite:
            break
        turn = _rodrigues(step[:3])
        for i in range(3):
            for j in range(3):
                turned[i, j] = turn[i, 0] * R[0, j] + turn[i, 1] * R[1, j] + turn[i, 2] * R[2, j]
        R[:] = turned
        for i in range(3):
            t[i] += step[3 + i]
        if step[0] * step[0] + step[1] * step[1] + step[2] * step[2] + step[3] * step[3] + step[4] * step[4] \
                + step[5] * step[5] < 1e-14:
            break


@njit(nogil=True, cache=True)
def refine_rounds_kernel(R: np.ndarray, t: np.ndarray, view_directions: np.ndarray, model_center: np.ndarray,
                         cell_starts: np.ndarray, cell_views: np.ndarray, seg_offsets: np.ndarray, seg_3d: np.ndarray,
                         image_2d: np.ndarray, image_lines: np.ndarray, tolerance: float, factors: np.ndarray,
                         rough_iterations: int, fine_iterations: int, min_cos: float) -> None:
    """``refinement.PoseRefiner.refine`` of poses R (B, 3, 3), t (B, 3), in place: per
    pose and round, the graph view nearest to the pose (``AspectGraph.nearest_views``, its
    ``view_cells`` as ``cell_starts``, ``cell_views``), its
    segments seg_3d (S, 2, 3) projected and paired with their nearest image segments
    (``nearest_lines`` at ``factors[round] * tolerance``, normalised units), then the
    Gauss-Newton steps on the pairs (``refine_poses``: Huber at ``tolerance``,
    ``rough_iterations`` in a round with a factor above 1, else ``fine_iterations``). A
    pose behind the camera stops; a round with fewer than 3 pairs leaves the pose as it
    is. One call per chunk of poses, GIL released throughout: as numpy it was a few dozen
    short steps per round, each holding the GIL.
    """
    i_ux, i_uy = _unit_directions(image_2d)
    largest = 0
    for v in range(len(seg_offsets) - 1):
        largest = max(largest, seg_offsets[v + 1] - seg_offsets[v])
    projected = np.empty((largest, 2, 2))
    best, best_cost = np.empty(largest, np.int64), np.empty(largest)
    points = np.empty((2 * largest, 3))
    lines = np.empty((largest, 3))
    weights = np.ones(largest)
    normal, variance = np.empty((6, 6)), np.empty(1)
    for b in range(len(R)):
        for factor in factors:
            if not t[b, 2] > 0:
                break
            view = _nearest_view(R[b], t[b], view_directions, model_center, cell_starts, cell_views)
            lo, hi = seg_offsets[view], seg_offsets[view + 1]
            for s in range(hi - lo):
                for e in range(2):
                    px, py, pz = seg_3d[lo + s, e, 0], seg_3d[lo + s, e, 1], seg_3d[lo + s, e, 2]
                    x = R[b, 0, 0] * px + R[b, 0, 1] * py + R[b, 0, 2] * pz + t[b, 0]
                    y = R[b, 1, 0] * px + R[b, 1, 1] * py + R[b, 1, 2] * pz + t[b, 1]
                    z = max(R[b, 2, 0] * px + R[b, 2, 1] * py + R[b, 2, 2] * pz + t[b, 2], 1e-9)
                    projected[s, e, 0], projected[s, e, 1] = x / z, y / z
            _nearest_lines(projected[:hi - lo], image_2d, i_ux, i_uy, factor * tolerance, min_cos, best, best_cost)
            pairs = 0
            for s in range(hi - lo):
                if best[s] >= 0:
                    points[2 * pairs] = seg_3d[lo + s, 0]
                    points[2 * pairs + 1] = seg_3d[lo + s, 1]
                    lines[pairs] = image_lines[best[s]]
                    pairs += 1
            if pairs >= 3:
                _gauss_newton(R[b], t[b], points, lines, 2, weights, 0, 2 * pairs, tolerance,
                              rough_iterations if factor > 1 else fine_iterations, normal, variance)

@njit(nogil=True, cache=True)
def _pairwise_sum(values: np.ndarray, n: int) -> np.float32:
    """numpy's float32 sum of values[:n] (n <= 128), in numpy's order to the bit: one
    running sum below 8 values, else 8 interleaved partial sums combined as a tree."""
    if n < 8:
        total = np.float32(-0.0)
        for i in range(n):
            total += values[i]
        return total
    partial = values[:8].copy()
    i = 8
    while i < n - n % 8:
        for k in range(8):
            partial[k] += values[i + k]
        i += 8
    total = ((partial[0] + partial[1]) + (partial[2] + partial[3])) + ((partial[4] + partial[5])
                                                                         + (partial[6] + partial[7]))
    while i < n:
        total += values[i]
        i += 1
    return total


@njit(nogil=True, cache=True)
def chamfer_scores_kernel(maps: np.ndarray, points: np.ndarray, orientations: np.ndarray, stride: int,
                          views: np.ndarray, phis: np.ndarray, cos_phi: np.ndarray, sin_phi: np.ndarray,
                          extent: float, cell: float, truncate: float, out: np.ndarray) -> None:
    """``prefilter.ChamferPrefilter``'s score of rows k (view ``views[k]`` at rotations
    ``phis[k]``, reduced to [0, 2 pi), with their float32 cosines and sines) into out (K, R):
    the mean over every ``stride``-th of the view's points (at most 128) of the truncated
    distance map ``maps`` (ORIENT_BINS, GRID, GRID) of the point's direction bin. float32
    throughout, step for step the numpy version's arithmetic, so the scores agree to the bit.
    """
    n_bins, grid = maps.shape[0], maps.shape[1]
    flat = maps.ravel()
    extent32, cell32, truncate32 = np.float32(extent), np.float32(cell), np.float32(truncate)
    pi32, two_pi32, bins32 = np.float32(math.pi), np.float32(2.0 * math.pi), np.float32(n_bins)
    n_points = (points.shape[1] + stride - 1) // stride
    distances = np.empty(n_points, np.float32)
    for k in range(len(views)):
        v = views[k]
        for r in range(phis.shape[1]):
            c, s, phi = cos_phi[k, r], sin_phi[k, r], phis[k, r]
            for q in range(n_points):
                x, y = points[v, q * stride, 0], points[v, q * stride, 1]
                xr, yr = c * x - s * y, s * x + c * y
                if abs(xr) > extent32 or abs(yr) > extent32:
                    distances[q] = truncate32
                    continue
                col = min(max(int((xr + extent32) / cell32), 0), grid - 1)
                row = min(max(int((yr + extent32) / cell32), 0), grid - 1)
                turned = orientations[v, q * stride] + phi
                turned -= pi32 * (np.float32(turned >= pi32) + np.float32(turned >= two_pi32))
                direction = int(turned / pi32 * bins32) % n_bins
                distances[q] = flat[(direction * grid + row) * grid + col]
            # np.mean divides the float32 sum by its int64 count in float64
            out[k, r] = np.float32(np.float64(_pairwise_sum(distances, n_points)) / n_points)


def warm_up() -> None:
    """Compile (or load from the cache) every kernel on a tiny input."""
    R, t = np.eye(3)[None].copy(), np.array([[0.0, 0.0, 1.0]])
    points = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.1, 0.1, 0.0]])
    lines = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, -0.1], [0.0, 1.0, -0.1]])
    refine_poses_kernel(R, t, points, lines, 1, np.ones(4), np.array([0, 4]), np.ones(1, np.bool_), np.full(1, 0.01), 2,
                        np.zeros((1, 6, 6)), np.zeros(1))
    segments = np.array([[[0.0, 0.0], [1.0, 0.0]], [[0.0, 0.1], [1.0, 0.1]]])
    nearest_lines_kernel(segments, segments, 0.5, 0.9, np.empty(2, np.int64), np.empty(2))
    square = np.array([[[-0.1, -0.1, 0.0], [0.1, -0.1, 0.0]], [[0.1, -0.1, 0.0], [0.1, 0.1, 0.0]],
                       [[0.1, 0.1, 0.0], [-0.1, 0.1, 0.0]], [[-0.1, 0.1, 0.0], [-0.1, -0.1, 0.0]]])
    drawn = square[..., :2] * 1.01
    cells = np.arange(7, dtype=np.int64), np.zeros(6, np.int64)  # one view in each of the 6 cells of n = 1
    refine_rounds_kernel(R, t, np.array([[0.0, 0.0, -1.0]]), np.zeros(3), *cells, np.array([0, 4]), square, drawn,
                         np.ones((4, 3)), 0.01, np.array([2.0, 1.0]), 1, 1, 0.9)
    from . import matching, prefilter  # here, not at the top: they import this module
    matching.align(segments, np.array([0, 2]), np.zeros(1, np.int64), np.zeros(1), segments, np.array([0, 2]),
                   np.zeros(1, np.int64), MatchParams())
    prefilter.ranked_peaks(np.zeros((1, 4)), 1, np.empty((1, 1), np.int64))
    phis = np.zeros((1, 2), np.float32)
    chamfer_scores_kernel(np.zeros((6, 4, 4), np.float32), np.zeros((1, 2, 2), np.float32),
                          np.zeros((1, 2), np.float32), 1, np.zeros(1, np.int64), phis, np.cos(phis), np.sin(phis),
                          2.0, 1.0, 0.25, np.empty((1, 2), np.float32))
    align_on_edges_kernel(R, t, np.array([[2.0]]), np.array([[0.0, 0.0, -1.0]]), np.zeros(3), *cells,
                          np.array([0, 4]), square, np.zeros(4, np.uint8), np.ones(3),
                          np.array([100.0, 100.0, 2.0, 2.0]), np.zeros(8),
                          np.zeros((8, 4, 4), np.int32), np.zeros(2, np.int64), np.zeros((1, 2)), 3.0, 12, 3,
                          np.zeros((1, 6, 6)), np.zeros(1))
    nearest_views_kernel(R, t, np.eye(3), np.zeros(3), *cells, np.zeros(1, np.int64))
    connected_labels(2, np.zeros(1, np.int64), np.ones(1, np.int64))
    gradient = np.ones((4, 4), np.float32)
    scaled_int16(gradient, gradient, 16.0)
    median_of_every_other(gradient)
    edge_runs_kernel(segments * 3.0, np.full((4, 4), 255, np.uint8), 2.0, 1.0, 1.0)
    near, row_starts, columns = np.zeros((1, 8, 6, 6), np.uint8), np.zeros(5, np.int64), np.zeros(0, np.int64)
    window = np.array([0, 0, 4, 4], np.int64)
    pose_evidence_kernel(segments * 3.0, np.zeros(2, np.int64), np.array([0, 2]), 1.0, near,
                         np.zeros((1, 8, 6, 6), np.float32), window, row_starts, columns, np.ones(1), 1.0, 0.2, 2, 1,
                         0, np.zeros((1, 5)), np.zeros((0, 0), np.uint8))
    run_on_kernel(segments * 3.0, np.array([0, 2]), near, np.zeros((1, 8, 6, 6), np.float32), window, 0.25, 6.0,
                  30.0, 10.0, 3.0, np.zeros((1, 3)))


@njit(nogil=True, cache=True)
def nearest_lines_kernel(model_2d: np.ndarray, image_2d: np.ndarray, tolerance: float, min_cos: float,
                         best: np.ndarray, best_cost: np.ndarray) -> None:
    """``lines2d.nearest_lines`` per model segment: best[i] the image segment whose end
    points lie closest to model line i (-1 if none qualifies), best_cost[i] that distance.
    The pairs are those of the former numpy matrices; the distances may differ from theirs
    in the last bit (BLAS fused its multiply-adds). A pair failing the angle test costs no
    more arithmetic."""
    i_ux, i_uy = _unit_directions(image_2d)
    _nearest_lines(model_2d, image_2d, i_ux, i_uy, tolerance, min_cos, best, best_cost)


@njit(nogil=True, cache=True)
def _unit_directions(segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction (x, y) of each segment (N, 2, 2)."""
    ux, uy = np.empty(segments.shape[0]), np.empty(segments.shape[0])
    for j in range(segments.shape[0]):
        dx, dy = segments[j, 1, 0] - segments[j, 0, 0], segments[j, 1, 1] - segments[j, 0, 1]
        length = max(math.hypot(dx, dy), 1e-12)
        ux[j], uy[j] = dx / length, dy / length
    return ux, uy


@njit(nogil=True, cache=True)
def _nearest_lines(model_2d: np.ndarray, image_2d: np.ndarray, i_ux: np.ndarray, i_uy: np.ndarray, tolerance: float,
                   min_cos: float, best: np.ndarray, best_cost: np.ndarray) -> None:
    """``nearest_lines_kernel`` with the image segments' unit directions given."""
    n_image = image_2d.shape[0]
    for i in range(model_2d.shape[0]):
        best[i], best_cost[i] = -1, np.inf
        ax, ay = model_2d[i, 0, 0], model_2d[i, 0, 1]
        dx, dy = model_2d[i, 1, 0] - ax, model_2d[i, 1, 1] - ay
        length = math.hypot(dx, dy)
        if not length > 1e-12:
            continue
        ux, uy = dx / length, dy / length
        nx, ny = -uy, ux
        along_origin, normal_origin = ux * ax + uy * ay, nx * ax + ny * ay
        for j in range(n_image):
            if not abs(ux * i_ux[j] + uy * i_uy[j]) > min_cos:
                continue
            p0x, p0y, p1x, p1y = image_2d[j, 0, 0], image_2d[j, 0, 1], image_2d[j, 1, 0], image_2d[j, 1, 1]
            perp = max(abs(nx * p0x + ny * p0y - normal_origin), abs(nx * p1x + ny * p1y - normal_origin))
            if not (perp < tolerance and perp < best_cost[i]):
                continue
            start, end = ux * p0x + uy * p0y - along_origin, ux * p1x + uy * p1y - along_origin
            if min(max(start, end), length) > max(min(start, end), 0.0):
                best[i], best_cost[i] = j, perp


@njit(nogil=True, cache=True)
def pose_evidence_kernel(model_px: np.ndarray, reach_of: np.ndarray, spans: np.ndarray, min_size: float,
                         near: np.ndarray, chance: np.ndarray, window: np.ndarray, row_starts: np.ndarray,
                         columns: np.ndarray, tolerances: np.ndarray, min_margin: float, margin_share: float, cell: int,
                         reach: int, seen_layer: int, out: np.ndarray, labels: np.ndarray) -> None:
    """What ``scoring.EdgeEvidence.shares`` counts for B poses, into ``out`` (B, 5): pose b's
    projected visible model segments are ``model_px[spans[b]:spans[b + 1]]`` (pixels),
    segment s looked up within ``tolerances[reach_of[s]]``, cells seen also by layer
    ``seen_layer`` of the maps, if >= 0, the maps over their ``window`` (``_pose_evidence``).

    A pose without segments, or whose segments span less than ``min_size`` pixels
    (diagonal of their box), keeps zeros. The rest are clipped a few image sizes out (a pose
    far off projects far outside; clipped, the outline stays what it covers of the image),
    outlined (``grown_outline``) and counted (``_pose_evidence``). One call for a batch of
    poses, GIL released: per pose in numpy, the projection, outline and clipping cost more
    than the counting and held the GIL. ``labels`` as ``_pose_evidence``'s.
    """
    height, width = window[2], window[3]
    far = float(max(height, width))
    for b in range(len(spans) - 1):
        out[b, :] = 0.0
        lo, hi = spans[b], spans[b + 1]
        if hi <= lo:
            continue
        points = model_px[lo:hi].reshape(-1, 2)
        x_lo, x_hi, y_lo, y_hi = np.inf, -np.inf, np.inf, -np.inf
        for i in range(points.shape[0]):
            x_lo, x_hi = min(x_lo, points[i, 0]), max(x_hi, points[i, 0])
            y_lo, y_hi = min(y_lo, points[i, 1]), max(y_hi, points[i, 1])
        if math.hypot(x_hi - x_lo, y_hi - y_lo) < min_size:
            continue
        clipped = np.minimum(np.maximum(model_px[lo:hi], -4.0 * far), 5.0 * far)
        _pose_evidence(clipped, reach_of[lo:hi], near, chance, window, row_starts, columns,
                       grown_outline(clipped.reshape(-1, 2), min_margin, margin_share), tolerances, cell, reach,
                       seen_layer, out[b], labels)


@njit(nogil=True, cache=True)
def grown_outline(points: np.ndarray, min_margin: float, margin_share: float) -> np.ndarray:
    """(K, 2) corners of the convex hull of points (N, 2), grown about their mean by
    ``margin_share`` of their root-mean-square distance from it, at least ``min_margin``.
    The hull is OpenCV's ``convexHull`` of the points as float32 (the same corners, no
    collinear ones; the order may start elsewhere), by Andrew's monotone chain."""
    n = points.shape[0]
    rounded = np.empty((n, 2))
    for i in range(n):
        rounded[i, 0], rounded[i, 1] = np.float32(points[i, 0]), np.float32(points[i, 1])
    order = np.argsort(rounded[:, 1], kind="mergesort")
    order = order[np.argsort(rounded[order, 0], kind="mergesort")]  # by x, then y
    chain = np.empty(2 * n + 1, np.int64)
    size = 0
    for half in range(2):  # the lower chain left to right, then the upper right to left
        start = size
        for k in range(n):
            i = order[k] if half == 0 else order[n - 1 - k]
            while size - start >= 2:
                o, a = chain[size - 2], chain[size - 1]
                cross = ((rounded[a, 0] - rounded[o, 0]) * (rounded[i, 1] - rounded[o, 1])
                         - (rounded[a, 1] - rounded[o, 1]) * (rounded[i, 0] - rounded[o, 0]))
                if cross > 0.0:
                    break
                size -= 1
            chain[size] = i
            size += 1
        size -= 1  # each chain's last point starts the other
    first, last = rounded[order[0]], rounded[order[n - 1]]
    if first[0] == last[0] and first[1] == last[1]:
        size = 1  # all points alike: one corner
    hull = rounded[chain[:max(size, 1)]]
    center = np.zeros(2)
    for i in range(len(hull)):
        center += hull[i]
    center /= len(hull)
    spread = 0.0
    for i in range(len(hull)):
        spread += (hull[i, 0] - center[0]) ** 2 + (hull[i, 1] - center[1]) ** 2
    radius = max(math.sqrt(spread / len(hull)), 1.0)
    return center + (1.0 + max(margin_share, min_margin / radius)) * (hull - center)


@njit(nogil=True, cache=True)
def _mark_segments(model_px: np.ndarray, left: int, top: int, marked: np.ndarray) -> None:
    """Mark a point every pixel along each segment (S, 2, 2) on ``marked``, a grid whose
    cell (0, 0) is pixel (left, top); points off the grid are skipped."""
    rows, cols = marked.shape
    for s in range(model_px.shape[0]):
        ax, ay = model_px[s, 0, 0], model_px[s, 0, 1]
        dx, dy = model_px[s, 1, 0] - ax, model_px[s, 1, 1] - ay
        count = min(max(int(math.ceil(math.sqrt(dx * dx + dy * dy))), 1), 4000)
        for j in range(count + 1):
            cx, cy = int(np.rint(ax + j / count * dx)) - left, int(np.rint(ay + j / count * dy)) - top
            if 0 <= cx < cols and 0 <= cy < rows:
                marked[cy, cx] = True


@njit(nogil=True, cache=True)
def _disc_offsets(radius: float, row_length: int) -> np.ndarray:
    """The offsets of the pixels within ``radius`` of a pixel in a flat grid of ``row_length``
    columns, rows from the top: read as one index each (walking a list of (x, y) pairs cost
    the run-on probes a sixth more)."""
    whole = int(math.floor(radius))
    offsets = np.empty((2 * whole + 1) ** 2, np.int64)
    count = 0
    for oy in range(-whole, whole + 1):
        for ox in range(-whole, whole + 1):
            if ox * ox + oy * oy <= radius * radius:
                offsets[count] = oy * row_length + ox
                count += 1
    return offsets[:count]


@njit(nogil=True, cache=True)
def _pose_evidence(model_px: np.ndarray, reach_of: np.ndarray, near: np.ndarray, chance: np.ndarray,
                   window: np.ndarray, row_starts: np.ndarray, columns: np.ndarray, outline: np.ndarray,
                   tolerances: np.ndarray, cell: int, reach: int, seen_layer: int, out: np.ndarray,
                   labels: np.ndarray) -> None:
    """What ``scoring.EdgeEvidence.shares`` counts for one pose, into ``out`` (5,).

    model_px (S, 2, 2) the projected visible model segments, pixels; segment s is looked up
    within ``tolerances[reach_of[s]]`` pixels and drawn within ``tolerance = tolerances[0]``;
    near (T, BINS, rows, cols) 0/1 per tolerance and direction bin, within that tolerance
    of a like edge pixel, and chance (T, BINS, rows, cols) the local share of such pixels,
    both over the ``window`` of the image with a border of 0 (``scoring.LookUpMaps``, H x W
    the image's ``window[2:]``); the edge pixels of row y at the columns
    ``columns[row_starts[y]:row_starts[y + 1]]`` (ascending); outline (P, 2) the grown convex
    outline's corners.

    out[0] the model length sampled (a point every 2 pixels, at most 2,000 per segment),
    out[1] the length a like edge pixel confirms, out[2] the length chance would confirm;
    out[3] the edge pixels inside the outline in seen cells, out[4] those of them within
    ``tolerance`` of a model segment. A cell (a ``cell``-pixel square) is seen when the
    model length confirmed in it, less what chance confirms, is at least half the model
    length in it, at the segments' own tolerances or at layer ``seen_layer`` of the maps if >= 0
    (a wider one: the edges of a feature the pose is turned a little off lie beside it), or,
    holding none, in the cells within ``reach`` of it: where the model's own edges are
    missing, or confirmed no more than chance would (dense texture), an occluder may be in
    front, and its edges say nothing against the pose.

    labels (H, W) uint8, or (0, 0) to skip: each edge pixel counted in out[3] marked 1, or 2
    when also counted in out[4] (pictures of what the explained share counts).
    """
    out[:] = 0.0
    bins, height, width = near.shape[1], window[2], window[3]
    tolerance = tolerances[0]
    rows, cols = (height + cell - 1) // cell, (width + cell - 1) // cell
    cell_model = np.zeros((rows, cols))
    cell_confirmed = np.zeros((rows, cols))
    cell_chance = np.zeros((rows, cols))
    wide_confirmed = np.zeros((rows, cols))
    wide_chance = np.zeros((rows, cols))
    # the sums in locals, added in the same order: kept in registers rather than in ``out``
    length_sum, confirmed_sum, chance_sum = 0.0, 0.0, 0.0
    for s in range(model_px.shape[0]):
        ax, ay = model_px[s, 0, 0], model_px[s, 0, 1]
        dx, dy = model_px[s, 1, 0] - ax, model_px[s, 1, 1] - ay
        length = math.sqrt(dx * dx + dy * dy)
        count = min(max(int(math.ceil(length / 2.0)), 1), 2000)
        weight = length / count
        b = _direction_bin(dx, dy, bins)
        k = reach_of[s]
        for j in range(count):
            frac = (j + 0.5) / count
            px, py = ax + frac * dx, ay + frac * dy
            x = min(max(int(np.rint(px)) + 1, 0), width + 1)
            y = min(max(int(np.rint(py)) + 1, 0), height + 1)
            my, mx = _in_window(x, y, window, near)
            confirmed = near[k, b, my, mx] != 0
            by_chance = weight * chance[k, b, my, mx]
            length_sum += weight
            chance_sum += by_chance
            if confirmed:
                confirmed_sum += weight
            if 1 <= x <= width and 1 <= y <= height:
                r, c = (y - 1) // cell, (x - 1) // cell
                cell_model[r, c] += weight
                cell_chance[r, c] += by_chance
                if confirmed:
                    cell_confirmed[r, c] += weight
                if seen_layer >= 0:
                    wide_chance[r, c] += weight * chance[seen_layer, b, my, mx]
                    if near[seen_layer, b, my, mx] != 0:
                        wide_confirmed[r, c] += weight
    out[0], out[1], out[2] = length_sum, confirmed_sum, chance_sum
    # the outline's bounding box in the image
    x0, y0, x1, y1 = width, height, 0, 0
    for i in range(outline.shape[0]):
        x0 = min(x0, int(math.floor(outline[i, 0])))
        x1 = max(x1, int(math.ceil(outline[i, 0])) + 1)
        y0 = min(y0, int(math.floor(outline[i, 1])))
        y1 = max(y1, int(math.ceil(outline[i, 1])) + 1)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
    if x1 <= x0 or y1 <= y0:
        return
    seen = np.zeros((rows, cols), np.bool_)
    for r in range(y0 // cell, (y1 - 1) // cell + 1):
        for c in range(x0 // cell, (x1 - 1) // cell + 1):
            model, confirmed, expected = cell_model[r, c], cell_confirmed[r, c], cell_chance[r, c]
            wide, wide_expected = wide_confirmed[r, c], wide_chance[r, c]
            if model == 0.0:  # no model edge here: judged by the cells around it
                for rr in range(max(r - reach, 0), min(r + reach + 1, rows)):
                    for cc in range(max(c - reach, 0), min(c + reach + 1, cols)):
                        model += cell_model[rr, cc]
                        confirmed += cell_confirmed[rr, cc]
                        expected += cell_chance[rr, cc]
                        wide += wide_confirmed[rr, cc]
                        wide_expected += wide_chance[rr, cc]
            seen[r, c] = model > 0.0 and (confirmed - expected >= 0.5 * model
                                          or (seen_layer >= 0 and wide - wide_expected >= 0.5 * model))
    # a point every pixel along the model, marked on a grid of the box grown by the tolerance;
    # an edge pixel is near the model if a point lies within the tolerance of it: looked up
    # for the counted edge pixels only, fewer than the points times the disc around each
    radius = int(math.floor(tolerance))
    marked = np.zeros((y1 - y0 + 2 * radius, x1 - x0 + 2 * radius), np.bool_)
    _mark_segments(model_px, x0 - radius, y0 - radius, marked)
    flat, disc = marked.reshape(-1), _disc_offsets(tolerance, marked.shape[1])
    # edge pixels inside the convex outline, row by row: each row's span from the outline's sides
    # that cross it, each side walked once over its rows (not every side tested at every row)
    corners = outline.shape[0]
    lefts, rights = np.full(y1 - y0, np.inf), np.full(y1 - y0, -np.inf)
    for i in range(corners):
        ax, ay = outline[i, 0], outline[i, 1]
        bx, by = outline[(i + 1) % corners, 0], outline[(i + 1) % corners, 1]
        # the rows y with min(ay, by) <= y < max(ay, by)
        for y in range(max(int(math.ceil(min(ay, by))), y0), min(int(math.ceil(max(ay, by))), y1)):
            x = ax + (y - ay) * (bx - ax) / (by - ay)
            lefts[y - y0], rights[y - y0] = min(lefts[y - y0], x), max(rights[y - y0], x)
    for y in range(y0, y1):
        left, right = lefts[y - y0], rights[y - y0]
        if right < left:
            continue
        # the row's edge pixels only: a few in a hundred pixels of the box
        lo, hi = max(int(math.ceil(left)), x0), min(int(math.floor(right)) + 1, x1)
        for k in range(row_starts[y], row_starts[y + 1]):
            x = columns[k]
            if x >= hi:
                break
            if x >= lo and seen[y // cell, x // cell]:
                near_model = False
                at = (y - y0 + radius) * marked.shape[1] + x - x0 + radius
                for d in range(len(disc)):
                    if flat[at - disc[d]]:
                        near_model = True
                        break
                out[3] += 1.0
                if near_model:
                    out[4] += 1.0
                if labels.shape[0] > 0:
                    labels[y, x] = 2 if near_model else 1


@njit(nogil=True, cache=True)
def _in_window(x: int, y: int, window: np.ndarray, maps: np.ndarray) -> tuple[int, int]:
    """The (row, column) of ``maps`` (..., rows, cols) over the ``window`` (``_pose_evidence``)
    that holds pixel (x, y) of the bordered image, clipped into the window: its outermost
    rows and columns are 0, like the image's maps everywhere outside it."""
    return (min(max(y - window[0], 0), maps.shape[-2] - 1), min(max(x - window[1], 0), maps.shape[-1] - 1))


@njit(nogil=True, cache=True)
def _nearest_view(R: np.ndarray, t: np.ndarray, view_directions: np.ndarray, model_center: np.ndarray,
                  cell_starts: np.ndarray, cell_views: np.ndarray) -> int:
    """``AspectGraph.nearest_views`` of one pose R (3, 3), t (3,): the view the camera sees
    the part from, the largest product with R^T t + c (the first of equal ones). Only the
    views of its cell are compared (``viewsphere.direction_cells``: ``cell_starts``,
    ``cell_views``, ascending, so the first of equal products is the whole scan's), every
    view where there are no cells or the direction is not a finite non-zero vector."""
    dx = model_center[0] + R[0, 0] * t[0] + R[1, 0] * t[1] + R[2, 0] * t[2]
    dy = model_center[1] + R[0, 1] * t[0] + R[1, 1] * t[1] + R[2, 1] * t[2]
    dz = model_center[2] + R[0, 2] * t[0] + R[1, 2] * t[1] + R[2, 2] * t[2]
    cell = _direction_cell(dx, dy, dz, len(cell_starts) - 1)
    lo, hi = (cell_starts[cell], cell_starts[cell + 1]) if cell >= 0 else (0, len(view_directions))
    view, most = 0, -np.inf
    for c in range(lo, hi):
        v = cell_views[c] if cell >= 0 else c
        product = view_directions[v, 0] * dx + view_directions[v, 1] * dy + view_directions[v, 2] * dz
        if product > most:
            view, most = v, product
    return view


@njit(nogil=True, cache=True, inline="always")
def _direction_cell(dx: float, dy: float, dz: float, cells: int) -> int:
    """The cell of ``viewsphere.direction_cells`` (``cells`` = 6 n^2 of them) holding the
    direction (dx, dy, dz), or -1 if there are none or the direction is zero or not finite."""
    ax, ay, az = abs(dx), abs(dy), abs(dz)
    if ax >= ay and ax >= az:  # the faces' axes as viewsphere.CUBE_FACES orders them
        face, u, v, most = 0 if dx > 0 else 1, dy, dz, ax
    elif ay >= az:
        face, u, v, most = 2 if dy > 0 else 3, dx, dz, ay
    else:
        face, u, v, most = 4 if dz > 0 else 5, dx, dy, az
    if cells <= 0 or not (0.0 < most < np.inf):
        return -1
    n = int(np.sqrt(cells // 6) + 0.5)
    i = min(max(int((u / most + 1.0) * 0.5 * n), 0), n - 1)
    j = min(max(int((v / most + 1.0) * 0.5 * n), 0), n - 1)
    return (face * n + i) * n + j


@njit(nogil=True, cache=True)
def nearest_views_kernel(R: np.ndarray, t: np.ndarray, view_directions: np.ndarray, model_center: np.ndarray,
                         cell_starts: np.ndarray, cell_views: np.ndarray, out: np.ndarray) -> None:
    """``AspectGraph.nearest_views`` of B poses R (B, 3, 3), t (B, 3) into ``out`` (B,)."""
    for b in range(len(R)):
        out[b] = _nearest_view(R[b], t[b], view_directions, model_center, cell_starts, cell_views)


# project_point and undistort_point are inlined into align_on_edges_kernel, three calls a
# point, and test the length first: an empty ``distortion`` (a camera without) is then told
# at once, not by ``any`` per call (the kernel 0.92x its time on the occluded latency images)
@njit(nogil=True, cache=True, inline="always")
def project_point(x: float, y: float, z: float, intrinsics: np.ndarray, distortion: np.ndarray) -> tuple[float, float]:
    """``Camera.project_model`` of one camera-frame point: ``Camera.project`` without
    distortion, else OpenCV's ``projectPoints`` arithmetic (``distortion`` the 8 rational
    model coefficients k1 k2 p1 p2 k3 k4 k5 k6, zeros where the camera has fewer; none, or
    all zero, without distortion)."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    if len(distortion) == 0 or not distortion.any():
        return fx * x / z + cx, fy * y / z + cy
    k = distortion
    inverse = 1.0 / z if z != 0.0 else 1.0
    x, y = x * inverse, y * inverse
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    a1, a2, a3 = 2.0 * x * y, r2 + 2.0 * x * x, r2 + 2.0 * y * y
    radial = 1.0 + k[0] * r2 + k[1] * r4 + k[4] * r6
    inverse_radial = 1.0 / (1.0 + k[5] * r2 + k[6] * r4 + k[7] * r6)
    xd = x * radial * inverse_radial + k[2] * a1 + k[3] * a2
    yd = y * radial * inverse_radial + k[2] * a3 + k[3] * a1
    return xd * fx + cx, yd * fy + cy


@njit(nogil=True, cache=True, inline="always")
def undistort_point(u: float, v: float, intrinsics: np.ndarray, distortion: np.ndarray) -> tuple[float, float]:
    """``Camera.undistort`` of one pixel: OpenCV's ``undistortPoints`` arithmetic (5
    fixed-point iterations) with distortion, a plain division without."""
    fx, fy, cx, cy = intrinsics[0], intrinsics[1], intrinsics[2], intrinsics[3]
    if len(distortion) == 0 or not distortion.any():
        return (u - cx) / fx, (v - cy) / fy
    x0, y0 = (u - cx) * (1.0 / fx), (v - cy) * (1.0 / fy)
    x, y = x0, y0
    k = distortion
    for _ in range(5):
        r2 = x * x + y * y
        inverse = (1.0 + ((k[7] * r2 + k[6]) * r2 + k[5]) * r2) / (1.0 + ((k[4] * r2 + k[1]) * r2 + k[0]) * r2)
        if inverse < 0.0:
            return x0, y0
        delta_x = 2.0 * k[2] * x * y + k[3] * (r2 + 2.0 * x * x)
        delta_y = k[2] * (r2 + 2.0 * y * y) + 2.0 * k[3] * x * y
        x, y = (x0 - delta_x) * inverse, (y0 - delta_y) * inverse
    return x, y


@njit(nogil=True, cache=True)
def align_on_edges_kernel(R: np.ndarray, t: np.ndarray, radii: np.ndarray, view_directions: np.ndarray,
                          model_center: np.ndarray, cell_starts: np.ndarray, cell_views: np.ndarray,
                          seg_offsets: np.ndarray, seg_3d: np.ndarray, seg_kind: np.ndarray, kind_weights: np.ndarray,
                          intrinsics: np.ndarray, distortion: np.ndarray, labels: np.ndarray, origin: np.ndarray,
                          pixels: np.ndarray, spacing: float, min_points: int, iterations: int,
                          normal_out: np.ndarray, variance_out: np.ndarray) -> None:
    """``refinement.align_on_edges`` of poses R (B, 3, 3), t (B, 3), in place: per pose
    and pairing k with ``radii[b, k]`` > 0, the visible segments of the nearest view (of its
    cell's, ``_nearest_view``) projected (``project_point``), a point every ``spacing`` pixels
    along each, paired with the nearest like-oriented edge pixel (``labels`` (BINS, rows, cols) from ``origin``, rows of
    ``pixels`` (L, 2), ``EdgeEvidence.nearest_like``, reaching every radius) within the
    radius, the line through that pixel along the model edge (``undistort_point``), then
    ``iterations`` Gauss-Newton steps with Huber at half the radius, each pair weighted by
    its segment's kind (``kind_weights[seg_kind]``, read here: the whole graph's weights
    gathered for each call cost 0.13 ms at 2,500 views). A pose behind the camera or with a
    visible edge at or behind the camera's plane, or pairing fewer than ``min_points``,
    stops for good. normal_out (B, 6, 6) and
    variance_out (B,) as ``refine_poses_kernel``'s. One call per chunk of poses, GIL
    released: as numpy it was some thirty array steps per pairing, holding the GIL.
    """
    bins = labels.shape[0]
    focal = (intrinsics[0] + intrinsics[1]) / 2.0
    for b in range(len(R)):
        for k in range(radii.shape[1]):
            depth = R[b, 2, 0] * model_center[0] + R[b, 2, 1] * model_center[1] + R[b, 2, 2] * model_center[2]
            if not depth + t[b, 2] > 0:
                break
            radius = radii[b, k]
            if not radius > 0:
                continue
            view = _nearest_view(R[b], t[b], view_directions, model_center, cell_starts, cell_views)
            lo, hi = seg_offsets[view], seg_offsets[view + 1]
            # the points of every segment first, to size the arrays of the pairs
            ends = np.empty((hi - lo, 2, 2))
            counts = np.empty(hi - lo, np.int64)
            crossing = False
            for s in range(hi - lo):
                for e in range(2):
                    px, py, pz = seg_3d[lo + s, e, 0], seg_3d[lo + s, e, 1], seg_3d[lo + s, e, 2]
                    z = R[b, 2, 0] * px + R[b, 2, 1] * py + R[b, 2, 2] * pz + t[b, 2]
                    if not z > 0:  # not projected: at z 0 the division would raise
                        crossing = True
                        break
                    ends[s, e, 0], ends[s, e, 1] = project_point(
                        R[b, 0, 0] * px + R[b, 0, 1] * py + R[b, 0, 2] * pz + t[b, 0],
                        R[b, 1, 0] * px + R[b, 1, 1] * py + R[b, 1, 2] * pz + t[b, 1], z, intrinsics, distortion)
                if crossing:
                    break
                dx, dy = ends[s, 1, 0] - ends[s, 0, 0], ends[s, 1, 1] - ends[s, 0, 1]
                counts[s] = max(int(max(math.hypot(dx, dy), 1e-12) // spacing), 1)
            # an edge reaching the camera's plane projects through infinity: billions of points
            # to pair (a wild hypothesis 33 mm deep, 4 m aside, asked 49 GB); such a pose is
            # as lost as one behind the camera
            if crossing:
                break
            total = counts.sum()
            points = np.empty((total, 3))
            lines = np.empty((total, 3))
            weights = np.empty(total)
            found = 0
            for s in range(hi - lo):
                dx, dy = ends[s, 1, 0] - ends[s, 0, 0], ends[s, 1, 1] - ends[s, 0, 1]
                length = max(math.hypot(dx, dy), 1e-12)
                ux, uy = dx / length, dy / length
                direction = _direction_bin(dx, dy, bins)
                a, c = seg_3d[lo + s, 0], seg_3d[lo + s, 1]
                for j in range(counts[s]):
                    frac = (j + 0.5) / counts[s]
                    qx, qy, qz = a[0] + frac * (c[0] - a[0]), a[1] + frac * (c[1] - a[1]), a[2] + frac * (c[2] - a[2])
                    u, v = project_point(R[b, 0, 0] * qx + R[b, 0, 1] * qy + R[b, 0, 2] * qz + t[b, 0],
                                     R[b, 1, 0] * qx + R[b, 1, 1] * qy + R[b, 1, 2] * qz + t[b, 1],
                                     R[b, 2, 0] * qx + R[b, 2, 1] * qy + R[b, 2, 2] * qz + t[b, 2], intrinsics,
                                     distortion)
                    near, ex, ey = nearest_like_edge(labels, origin, pixels, direction, u, v, radius)
                    if not near:
                        continue
                    points[found, 0], points[found, 1], points[found, 2] = qx, qy, qz
                    x0, y0 = undistort_point(ex - ux, ey - uy, intrinsics, distortion)
                    x1, y1 = undistort_point(ex + ux, ey + uy, intrinsics, distortion)
                    # ``lines2d.line_equations`` of the segment through the two
                    sx, sy = x1 - x0, y1 - y0
                    norm = max(math.sqrt(sx * sx + sy * sy), 1e-12)
                    lines[found, 0], lines[found, 1] = -sy / norm, sx / norm
                    lines[found, 2] = -(lines[found, 0] * x0 + lines[found, 1] * y0)
                    weights[found] = kind_weights[seg_kind[lo + s]]
                    found += 1
            if total and found < min_points:
                break
            if found >= 3:
                _gauss_newton(R[b], t[b], points, lines, 1, weights, 0, found, 0.5 * radius / focal, iterations,
                              normal_out[b], variance_out[b:b + 1])


@njit(nogil=True, cache=True)
def nearest_like_edge(labels: np.ndarray, origin: np.ndarray, pixels: np.ndarray, direction: int, u: float,
                      v: float, radius: float) -> tuple[bool, float, float]:
    """For a point (u, v), pixels, on a model edge of direction bin ``direction``: whether
    the nearest edge pixel that runs alike (``EdgeEvidence.nearest_like``'s ``labels`` from
    ``origin``, rows of ``pixels``) lies within ``radius``, and where. An edge pixel of
    another direction nearer to the point does not hide it: a pose 10 degrees off sits
    among the part's crossing edges. A point outside the labels' window (within the image)
    has none within their reach, which the radius does not exceed."""
    col, row = int(np.rint(u)) - origin[1], int(np.rint(v)) - origin[0]
    if not (0 <= col < labels.shape[2] and 0 <= row < labels.shape[1]):
        return False, 0.0, 0.0
    edge = labels[direction, row, col]
    ex, ey = pixels[edge, 0], pixels[edge, 1]
    return math.hypot(ex - u, ey - v) <= radius, ex, ey


@njit(nogil=True, cache=True)
def _direction_bin(dx: float, dy: float, bins: int) -> int:
    """The direction bin (of ``bins`` over pi) of a segment running (dx, dy)."""
    return int(math.atan2(dy, dx) % math.pi / math.pi * bins) % bins


@njit(nogil=True, cache=True)
def run_on_kernel(segments: np.ndarray, spans: np.ndarray, near: np.ndarray, chance: np.ndarray, window: np.ndarray,
                  share: float, min_probe: float, max_probe: float, min_length: float, clear: float,
                  out: np.ndarray) -> None:
    """Where the image's edges run on past the ends of B poses' projected model edges, into
    ``out`` (B, 3): pose b's segments are ``segments[spans[b]:spans[b + 1]]`` (pixels).

    Beyond each end of every segment at least ``min_length`` long, along its direction, a
    probe a pixel apart from ``clear`` + 1 to ``clear`` + 1 + its length times ``share``
    (within ``min_probe`` - ``max_probe``) pixels out; probe points inside the image and
    farther than ``clear`` from every segment of the pose (a corner turns into the next
    model edge, a curve into its next piece: there the model itself has an edge) are
    counted. out[0] their number, out[1] those a like edge confirms (``near[0, bin]`` at the
    point, the segment's direction bin), out[2] the number chance would confirm (``chance``);
    the maps over their ``window`` as ``pose_evidence_kernel``'s.
    A pose too small or too far lies on pieces of the part's longer edges, which run on past
    its ends; occlusion cuts edges short and adds no run-on, clutter only by chance.
    """
    bins, height, width = near.shape[1], window[2], window[3]
    far = float(max(height, width))
    radius = int(math.floor(clear))
    reach = int(math.ceil(clear + 1.0 + max_probe)) + radius + 1
    for b in range(len(spans) - 1):
        out[b, :] = 0.0
        lo, hi = spans[b], spans[b + 1]
        if hi <= lo:
            continue
        # a pose far off projects far outside: clipped a few image sizes out, as pose_evidence_kernel does
        model_px = np.minimum(np.maximum(segments[lo:hi], -4.0 * far), 5.0 * far)
        x0, y0, x1, y1 = width, height, 0, 0
        for s in range(model_px.shape[0]):
            for e in range(2):
                x0, x1 = min(x0, int(math.floor(model_px[s, e, 0]))), max(x1, int(math.ceil(model_px[s, e, 0])) + 1)
                y0, y1 = min(y0, int(math.floor(model_px[s, e, 1]))), max(y1, int(math.ceil(model_px[s, e, 1])) + 1)
        x0, y0, x1, y1 = max(x0 - reach, 0), max(y0 - reach, 0), min(x1 + reach, width), min(y1 + reach, height)
        if x1 <= x0 or y1 <= y0:
            continue
        # the model's own pixels on a grid of the box, to keep probes off other model edges; the
        # grid has a border of ``radius`` never marked, so the disc about a probe needs no bounds checks
        marked = np.zeros((y1 - y0 + 2 * radius, x1 - x0 + 2 * radius), np.bool_)
        _mark_segments(model_px, x0, y0, marked[radius:radius + y1 - y0, radius:radius + x1 - x0])
        flat, disc = marked.reshape(-1), _disc_offsets(clear, marked.shape[1])
        for s in range(model_px.shape[0]):
            ax, ay = model_px[s, 0, 0], model_px[s, 0, 1]
            dx, dy = model_px[s, 1, 0] - ax, model_px[s, 1, 1] - ay
            length = math.sqrt(dx * dx + dy * dy)
            if length < min_length:
                continue
            ux, uy = dx / length, dy / length
            k = _direction_bin(dx, dy, bins)
            steps = int(min(max(share * length, min_probe), max_probe))
            for e in range(2):
                sign = 1.0 if e == 1 else -1.0
                ex, ey = model_px[s, e, 0], model_px[s, e, 1]
                for j in range(steps):
                    d = sign * (clear + 1.0 + j)
                    x, y = int(np.rint(ex + d * ux)), int(np.rint(ey + d * uy))
                    if not (x0 <= x < x1 and y0 <= y < y1):
                        continue
                    on_model = False
                    at = (y - y0 + radius) * marked.shape[1] + x - x0 + radius
                    for d in range(len(disc)):
                        if flat[at + disc[d]]:
                            on_model = True
                            break
                    if on_model:
                        continue
                    my, mx = _in_window(x + 1, y + 1, window, near)
                    out[b, 0] += 1.0
                    out[b, 1] += near[0, k, my, mx]
                    out[b, 2] += chance[0, k, my, mx]


@njit(nogil=True, cache=True)
def connected_labels(n: int, first: np.ndarray, second: np.ndarray) -> tuple[int, np.ndarray]:
    """``scipy.sparse.csgraph.connected_components(directed=False)`` of the graph of ``n``
    nodes and edges (first[k], second[k]): the number of components and each node's label,
    numbered by their lowest node as scipy numbers them. A union-find joining every root
    under the lower one; scipy's sparse matrices cost 0.15 ms a call on a few dozen line
    pieces (``image_edges.merge_segments``, several calls an image)."""
    root = np.arange(n)
    for k in range(len(first)):
        a, b = first[k], second[k]
        while root[a] != a:
            root[a] = root[root[a]]
            a = root[a]
        while root[b] != b:
            root[b] = root[root[b]]
            b = root[b]
        root[max(a, b)] = min(a, b)
    labels = np.empty(n, np.int32)
    count = 0
    for v in range(n):  # a root is its component's lowest node, labelled before the others
        r = v
        while root[r] != r:
            r = root[r]
        if r == v:
            labels[v] = count
            count += 1
        else:
            labels[v] = labels[r]
    return count, labels


@njit(nogil=True, cache=True)
def scaled_int16(dx: np.ndarray, dy: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """``np.round(d * scale).astype(np.int16)`` of two float32 maps (Canny's derivatives), in
    one pass: numpy's three passes each held the GIL 0.5 ms an image."""
    s = np.float32(scale)
    out_x, out_y = np.empty(dx.shape, np.int16), np.empty(dy.shape, np.int16)
    for i in range(dx.shape[0]):
        for j in range(dx.shape[1]):
            out_x[i, j] = np.int16(np.rint(dx[i, j] * s))  # rint rounds half to even, as np.round
            out_y[i, j] = np.int16(np.rint(dy[i, j] * s))
    return out_x, out_y


@njit(nogil=True, cache=True)
def median_of_every_other(magnitude: np.ndarray) -> np.float32:
    """``np.median(magnitude[::2, ::2])`` of a non-negative float32 map, to the bit: its middle
    values picked by their bit patterns, which order as non-negative floats do, in two
    16-bit counting passes (np.median's partition took 0.8 ms an image)."""
    sub = magnitude[::2, ::2]
    keys = np.empty(sub.size, np.float32)
    for i in range(sub.shape[0]):
        for j in range(sub.shape[1]):
            keys[i * sub.shape[1] + j] = sub[i, j]
    bits, n = keys.view(np.uint32), len(keys)
    middle = np.empty(2, np.uint32)
    middle[1] = _kth_smallest(bits, n // 2)
    middle[0] = middle[1] if n % 2 else _kth_smallest(bits, n // 2 - 1)
    values = middle.view(np.float32)
    # np.median's mean of the two: their float32 sum halved
    return values[1] if n % 2 else np.float32(values[0] + values[1]) / np.float32(2.0)


@njit(nogil=True, cache=True)
def _kth_smallest(keys: np.ndarray, k: int) -> np.uint32:
    """The k-th smallest (from 0) of uint32 keys: its high 16 bits by counting, then its low."""
    counts = np.zeros(1 << 16, np.int64)
    for key in keys:
        counts[key >> 16] += 1
    high = 0
    while k >= counts[high]:
        k -= counts[high]
        high += 1
    counts[:] = 0
    for key in keys:
        if key >> 16 == high:
            counts[key & 0xFFFF] += 1
    low = 0
    while k >= counts[low]:
        k -= counts[low]
        low += 1
    return np.uint32((high << 16) | low)


@njit(nogil=True, cache=True)
def edge_runs_kernel(segments: np.ndarray, edges: np.ndarray, distance: float, window: float, gap: float
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The sums of ``image_edges._refine_once``'s line fit, to the bit: per segment of non-zero
    length the edge pixels within ``distance`` of its line, from ``window`` before its first
    end point to ``window`` after its second, sorted along it; the run of them through the
    segment's own span, broken where pixels lie more than ``gap`` apart outside it. Returns
    the run's pixel count, centre (NaN without pixels), scatter sums (xx, xy, yy about the
    centre) and first and last pixel along the segment: numpy's lexsort, cumsums and
    bincounts here held the GIL ~6 ms an occluded image in many small passes. The angle of
    the scatter's axis stays numpy's (its arctan2, cos and sin)."""
    n = len(segments)
    owner, pixels, t = _pixels_along(segments, edges, distance, window)
    count = np.zeros(n, np.int64)
    centre, scatter = np.full((n, 2), np.nan), np.zeros((n, 3))
    ends = np.zeros((n, 2, 2))
    start = 0
    for s in range(n):
        stop = start
        while stop < len(owner) and owner[stop] == s:
            stop += 1
        dx, dy = segments[s, 1, 0] - segments[s, 0, 0], segments[s, 1, 1] - segments[s, 0, 1]
        length = np.sqrt(dx * dx + dy * dy)
        # the segment's own span counts as filled: its two ends as virtual points after the pixels
        along = np.empty(stop - start + 2)
        along[: stop - start] = t[start:stop]
        along[-2], along[-1] = 0.0, length
        order = np.argsort(along, kind="mergesort")  # stable, as np.lexsort
        run = np.empty(len(order), np.int64)
        core = 0
        for k in range(len(order)):
            run[k] = 0 if k == 0 else run[k - 1]
            if k > 0:
                previous, here = along[order[k - 1]], along[order[k]]
                inside = 0.0 <= previous <= length and 0.0 <= here <= length
                if here - previous > gap and not inside:
                    run[k] += 1
            if order[k] >= stop - start:
                core = run[k]
        kept = np.empty(len(order), np.int64)
        m = 0
        for k in range(len(order)):
            if order[k] < stop - start and run[k] == core:
                kept[m] = start + order[k]
                m += 1
        count[s] = m
        if m:
            # bincount's sums: in order, weight 1
            sx, sy = 0.0, 0.0
            for k in range(m):
                sx += pixels[kept[k], 0]
                sy += pixels[kept[k], 1]
            cx, cy = sx / m, sy / m
            xx, xy, yy = 0.0, 0.0, 0.0
            for k in range(m):
                ox, oy = pixels[kept[k], 0] - cx, pixels[kept[k], 1] - cy
                xx += ox * ox
                xy += ox * oy
                yy += oy * oy
            centre[s, 0], centre[s, 1] = cx, cy
            scatter[s, 0], scatter[s, 1], scatter[s, 2] = xx, xy, yy
            ends[s, 0] = pixels[kept[0]]
            ends[s, 1] = pixels[kept[m - 1]]
        start = stop
    return count, centre, scatter, ends


@njit(nogil=True, cache=True)
def _pixels_along(segments: np.ndarray, edges: np.ndarray, distance: float, window: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(owner, pixel (x, y), t) of the edge pixels within ``distance`` of each segment's line,
    t the position along it from its first end point, by segment, then along the major axis,
    then across. Stepping one pixel along the major axis and a few across it visits every
    pixel of the band exactly once per segment."""
    height, width = edges.shape
    half = int(distance * math.sqrt(2.0) + 0.5)  # |major_unit| >= 1/sqrt(2), plus rounding of the centre
    n = len(segments)
    lo, hi = np.zeros(n, np.int64), np.full(n, -1, np.int64)
    steep = np.zeros(n, np.bool_)
    first_x, first_y, unit_x, unit_y = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    for s in range(n):
        first_x[s], first_y[s] = segments[s, 0, 0], segments[s, 0, 1]
        dx, dy = segments[s, 1, 0] - first_x[s], segments[s, 1, 1] - first_y[s]
        length = np.sqrt(dx * dx + dy * dy)
        unit_x[s], unit_y[s] = dx / length, dy / length
        steep[s] = abs(unit_y[s]) > abs(unit_x[s])
        major_first, major_unit = (first_y[s], unit_y[s]) if steep[s] else (first_x[s], unit_x[s])
        start, end = major_first + -window * major_unit, major_first + (length + window) * major_unit
        lo[s] = int(max(np.ceil(min(start, end)), 0.0))
        hi[s] = int(min(np.floor(max(start, end)), float((height if steep[s] else width) - 1)))
    # two passes: count the hits, then fill arrays of that size
    owner = np.empty(0, np.int64)
    pixels = np.empty((0, 2))
    t = np.empty(0)
    for fill in range(2):
        count = 0
        for s in range(n):
            if steep[s]:
                major_first, minor_first, major_unit, minor_unit = first_y[s], first_x[s], unit_y[s], unit_x[s]
                minor_size = width
            else:
                major_first, minor_first, major_unit, minor_unit = first_x[s], first_y[s], unit_x[s], unit_y[s]
                minor_size = height
            for major in range(lo[s], hi[s] + 1):
                centre = int(np.rint(minor_first + (major - major_first) * minor_unit / major_unit))
                for minor in range(centre - half, centre + half + 1):
                    if minor < 0 or minor >= minor_size:
                        continue
                    x, y = (minor, major) if steep[s] else (major, minor)
                    if edges[y, x] == 0:
                        continue
                    ox, oy = x - first_x[s], y - first_y[s]
                    if abs(ox * unit_y[s] - oy * unit_x[s]) > distance:
                        continue
                    if fill:
                        owner[count] = s
                        pixels[count, 0], pixels[count, 1] = x, y
                        t[count] = ox * unit_x[s] + oy * unit_y[s]
                    count += 1
        if not fill:
            owner, pixels, t = np.empty(count, np.int64), np.empty((count, 2)), np.empty(count)
    return owner, pixels, t

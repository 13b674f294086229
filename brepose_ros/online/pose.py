"""Stage 5: from a matched view to a metric 6-DoF pose, and its refinement.

First pose (what the paper leaves out). A view is an orthographic picture of the part seen
along one direction. An off-centre part is not seen along the optical axis but along the
ray through it, so the image edges of a region are first turned onto a *virtual camera*
whose optical axis is that ray (a pure rotation of the rays, exact for a pinhole camera).
There the part is centred and its image is, to first order, the view scaled by 1/depth.
The similarity (scale k, rotation phi, shift tau) that maps the view's orthographic
coordinates (metres) onto the virtual image (normalised coordinates) then gives

    R = R_align @ Rz(phi) @ R_view,    t = R_align @ ([tau, 1] / k) - R @ c0

with c0 the model centre: depth comes from scale, not from a sampled camera distance.

Refinement. Every matched view segment carries its two 3D end points on the model; every
image segment is a line. A robust Gauss-Newton (Huber weights) over the 6 pose parameters pulls
the projected end points onto their image lines. Between rounds the visible edges of the
graph view nearest to the current pose are projected again and re-associated with the
image lines, with a tolerance that shrinks round by round.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from ..camera import Camera
from ..geometry import rot_z, rotation_between


def undistort_points(points_px: np.ndarray, camera: Camera) -> np.ndarray:
    """Pixels (N, 2) in normalised camera coordinates ((u - cx) / fx, (v - cy) / fy)."""
    pts = np.asarray(points_px, dtype=float).reshape(-1, 1, 2)
    if len(pts) == 0:
        return np.zeros((0, 2))
    if camera.has_distortion:
        return cv2.undistortPoints(pts, camera.K, camera.dist_coeffs).reshape(-1, 2)
    return (pts.reshape(-1, 2) - [camera.cx, camera.cy]) / [camera.fx, camera.fy]


def undistort_segments(segments_px: np.ndarray, camera: Camera) -> np.ndarray:
    """Image segments (N, 2, 2) in normalised camera coordinates."""
    return undistort_points(np.asarray(segments_px, dtype=float).reshape(-1, 2), camera).reshape(-1, 2, 2)


def virtual_alignment(center_normalised: np.ndarray) -> np.ndarray:
    """R_align: turns the virtual camera's optical axis onto the ray through the centre."""
    ray = np.array([center_normalised[0], center_normalised[1], 1.0])
    return rotation_between(np.array([0.0, 0.0, 1.0]), ray)


def to_virtual(normalised: np.ndarray, R_align: np.ndarray) -> np.ndarray:
    """Points (..., 2), e.g. segments (N, 2, 2), seen by the virtual camera R_align^T (rays
    rotated, then re-projected); the shape is kept."""
    normalised = np.asarray(normalised, dtype=float)
    pts = normalised.reshape(-1, 2)
    rays = np.concatenate([pts, np.ones((len(pts), 1))], axis=1) @ R_align  # R_align^T r
    return (rays[:, :2] / rays[:, 2:3]).reshape(normalised.shape)


def pose_from_similarity(R_view: np.ndarray, model_center: np.ndarray, scale: float,
                         phi: float, shift: np.ndarray, R_align: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T_cam_model from a view and the similarity view (metres) -> virtual image (module doc)."""
    R = R_align @ rot_z(phi) @ R_view
    center_virtual = np.array([shift[0], shift[1], 1.0]) / scale
    t = R_align @ center_virtual - R @ model_center
    return R, t


def project(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Normalised image coordinates of model points (…, 3); no distortion."""
    cam = np.asarray(points) @ R.T + t
    return cam[..., :2] / np.maximum(cam[..., 2:3], 1e-9)


def project_pixels(points: np.ndarray, R: np.ndarray, t: np.ndarray, camera: Camera) -> np.ndarray:
    """Pixel coordinates with the camera's distortion (for drawing and reporting)."""
    pts = np.asarray(points, dtype=float)
    flat = pts.reshape(-1, 3)
    if len(flat) == 0:
        return np.zeros(pts.shape[:-1] + (2,))
    rvec, _ = cv2.Rodrigues(np.asarray(R, dtype=float))
    out, _ = cv2.projectPoints(flat, rvec, np.asarray(t, dtype=float), camera.K, camera.dist_coeffs)
    return out.reshape(pts.shape[:-1] + (2,))


@dataclass
class LineMatches:
    """Model segments (3D) paired with image lines (normalised image coordinates)."""

    model_3d: np.ndarray  # (K, 2, 3)
    image_2d: np.ndarray  # (K, 2, 2)
    model_index: np.ndarray  # (K,) into the candidate model segments
    image_index: np.ndarray  # (K,) into the image segments
    distances: np.ndarray  # (K,) largest distance of the image end points to the model line


def line_equations(segments: np.ndarray) -> np.ndarray:
    """(K, 3) lines a x + b y + c = 0 with (a, b) a unit normal."""
    start = segments[:, 0]
    dx, dy = segments[:, 1, 0] - start[:, 0], segments[:, 1, 1] - start[:, 1]
    length = np.maximum(np.sqrt(dx * dx + dy * dy), 1e-12)
    lines = np.empty((len(segments), 3))
    lines[:, 0], lines[:, 1] = -dy / length, dx / length
    lines[:, 2] = -(lines[:, 0] * start[:, 0] + lines[:, 1] * start[:, 1])
    return lines


def associate(model_3d: np.ndarray, R: np.ndarray, t: np.ndarray, image_2d: np.ndarray,
              tolerance: float, max_angle_deg: float = 10.0) -> LineMatches:
    """Pair each projected model segment with the closest overlapping, parallel image line.

    Distances are in normalised image units (pixels / f); see ``nearest_lines``.
    """
    if len(model_3d) == 0 or len(image_2d) == 0:
        return LineMatches(np.zeros((0, 2, 3)), np.zeros((0, 2, 2)), np.zeros(0, int), np.zeros(0, int), np.zeros(0))
    mi, ii, dist = nearest_lines(project(model_3d, R, t), image_2d, tolerance, max_angle_deg)
    return LineMatches(model_3d[mi], image_2d[ii], mi, ii, dist)


def nearest_lines(model_2d: np.ndarray, image_2d: np.ndarray, tolerance: float,
                  max_angle_deg: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices (model, image) pairing each model segment with its best image segment, and
    the distance of each pair (largest distance of the image end points to the model line).

    A model segment keeps the image segment whose end points lie closest to the model's
    line, provided that is within ``tolerance``, the directions agree within
    ``max_angle_deg`` and the two overlap along the line.
    """
    if len(model_2d) == 0 or len(image_2d) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    n_model, n_image = len(model_2d), len(image_2d)
    m_dir = model_2d[:, 1] - model_2d[:, 0]
    m_len = np.hypot(m_dir[:, 0], m_dir[:, 1])
    m_unit = m_dir / np.maximum(m_len, 1e-12)[:, None]
    i_dir = image_2d[:, 1] - image_2d[:, 0]
    i_unit = i_dir / np.maximum(np.hypot(i_dir[:, 0], i_dir[:, 1]), 1e-12)[:, None]
    cos = np.abs(m_unit @ i_unit.T)
    # image end points in every model segment's frame (along its direction, along its
    # normal) by one matmul: columns are all first end points, then all second ones
    axes = np.concatenate([m_unit, m_unit[:, ::-1] * [-1.0, 1.0]])  # (2M, 2)
    origins = (axes.reshape(2, n_model, 2) * model_2d[:, 0]).sum(axis=2).reshape(-1, 1)
    coords = axes @ image_2d.transpose(2, 1, 0).reshape(2, -1) - origins
    along, normal = coords[:n_model], np.abs(coords[n_model:])
    perp = np.maximum(normal[:, :n_image], normal[:, n_image:])
    start, end = along[:, :n_image], along[:, n_image:]
    overlaps = np.minimum(np.maximum(start, end), m_len[:, None]) > np.maximum(np.minimum(start, end), 0.0)
    valid = (cos > _cos_deg(max_angle_deg)) & (perp < tolerance) & overlaps & (m_len > 1e-12)[:, None]
    cost = np.where(valid, perp, np.inf)
    best = np.argmin(cost, axis=1)
    best_cost = cost[np.arange(n_model), best]
    keep = best_cost < np.inf
    return np.nonzero(keep)[0], best[keep], best_cost[keep]


@lru_cache(maxsize=8)
def _cos_deg(angle_deg: float) -> float:
    """Cosine of a fixed angle, kept: ``nearest_lines`` runs thousands of times per image."""
    return float(np.cos(np.radians(angle_deg)))


def associate_poses(model_3d: np.ndarray, spans: np.ndarray, R: np.ndarray, t: np.ndarray,
                    image_2d: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``nearest_lines`` for B poses R (B, 3, 3), t (B, 3) at once: model segments
    ``spans[b]:spans[b + 1]`` belong to pose b. The pairing is decided segment by segment,
    so one call does the work of B; each pose projects its own segments as ``project``."""
    if len(model_3d) == 0 or len(image_2d) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    projected = np.empty(model_3d.shape[:-1] + (2,))
    for b, (lo, hi) in enumerate(zip(spans[:-1], spans[1:])):
        projected[lo:hi] = project(model_3d[lo:hi], R[b], t[b])
    return nearest_lines(projected, image_2d, tolerance)


def refine_poses(R: np.ndarray, t: np.ndarray, model_3d: np.ndarray, image_2d: np.ndarray, spans: np.ndarray,
                 f_scale: float, iterations: int = 8, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Robust Gauss-Newton on the point-to-line distances (normalised units), for B poses
    R (B, 3, 3), t (B, 3) at once: pairs (model points (K, P, 3), image line) ``spans[b]:spans[b + 1]``
    belong to pose b; the P points of a pair (a segment's 2 end points, or 1 sampled point)
    are pulled onto its line. Returns new arrays.

    Iteratively reweighted least squares with Huber weights (``f_scale`` is the Huber
    threshold) times the pair's ``weights`` (K,) if given (1 by default), an analytic
    Jacobian and the update R <- exp(w) R, t <- t + dt: six
    unknowns, so each step is a 6x6 solve per pose; far cheaper than a generic solver with
    numeric derivatives. It runs for every hypothesis and every neighbouring view the
    climb tries, on about a hundred points each, so numpy's per-call overhead is the cost:
    the element-wise work of all poses runs as one set of array operations (one column
    per end point, the cross product written out); only the products that sum over a
    pose's points, the 6x6 solves (OpenCV's Cholesky) and the rotations go pose by pose,
    with the very operations a single pose would use, so a pose refines to the same bits
    alone or in a batch. A pose with fewer than 3 pairs stays where it is; a pose stops
    once its step vanishes.
    """
    R, t = np.array(R, dtype=float), np.array(t, dtype=float)
    lines = line_equations(image_2d)  # (K, 3)
    per_pair = model_3d.shape[1]
    nx, ny, offsets = np.repeat(lines, per_pair, axis=0).T
    pair_weights = None if weights is None else np.repeat(np.asarray(weights, dtype=float), per_pair)
    points = model_3d.reshape(-1, 3).T  # (3, N)
    ends = per_pair * np.asarray(spans)  # point columns of each pose
    active = np.diff(spans) >= 3
    jac = np.empty((6, points.shape[1]))  # d residual / d (w, dt), one column per point
    rows = jac[3:]
    rotated = np.empty_like(points)
    moved = np.empty_like(points)
    for _ in range(iterations):
        if not active.any():
            break
        for b, (lo, hi) in enumerate(zip(ends[:-1], ends[1:])):
            rotated[:, lo:hi] = R[b] @ points[:, lo:hi]
            moved[:, lo:hi] = rotated[:, lo:hi] + t[b][:, None]
        x, y, z = moved
        z = np.maximum(z, 1e-9)
        along_normal = nx * (x / z) + ny * (y / z)
        residual = along_normal + offsets
        # d residual / d X_cam = g, then chain through X_cam = exp(w) R X + t:
        # g . (w x RX) = w . (RX x g)
        np.divide(nx, z, out=rows[0])
        np.divide(ny, z, out=rows[1])
        np.divide(along_normal, z, out=rows[2])
        np.negative(rows[2], out=rows[2])
        (r0, r1, r2), (g0, g1, g2) = rotated, rows
        np.subtract(r1 * g2, r2 * g1, out=jac[0])
        np.subtract(r2 * g0, r0 * g2, out=jac[1])
        np.subtract(r0 * g1, r1 * g0, out=jac[2])
        weight = f_scale / np.maximum(np.abs(residual), f_scale)  # Huber: 1 within f_scale
        weighted = jac * (weight if pair_weights is None else weight * pair_weights)
        for b in np.nonzero(active)[0]:
            lo, hi = ends[b], ends[b + 1]
            hessian = weighted[:, lo:hi] @ jac[:, lo:hi].T
            hessian.flat[::7] += 1e-6 * hessian.trace() / 6.0  # damping: degenerate line sets
            solved, step = cv2.solve(hessian, -(weighted[:, lo:hi] @ residual[lo:hi]), flags=cv2.DECOMP_CHOLESKY)
            step = step[:, 0]
            if not solved or not np.isfinite(step).all():
                active[b] = False
                continue
            R[b] = cv2.Rodrigues(step[:3])[0] @ R[b]
            t[b] = t[b] + step[3:]
            active[b] = step @ step >= 1e-14
    return R, t


def polish_pose(R: np.ndarray, t: np.ndarray, model_3d: np.ndarray, weights: np.ndarray,
                evidence: "EdgeEvidence", camera: Camera, radius_px: float, rounds: int,
                spacing_px: float, f_scale: float, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """Refine one pose on the Canny edge pixels rather than on the Hough lines.

    Points every ``spacing_px`` along the projected model segments (M, 2, 3) are paired
    with their nearest like-oriented edge pixel within ``radius_px``
    (``EdgeEvidence.nearest_edges``) and pulled onto the line through it along the model
    edge, weighted by ``weights`` (M,) per segment; re-paired each round. Every projected
    edge speaks, where the line refinement only hears edges the line detector found
    (6-12 on the rounded bracket, whose arcs and holes give no Hough lines).
    """
    for _ in range(rounds):
        ends_px = project_pixels(model_3d, R, t, camera)
        delta = ends_px[:, 1] - ends_px[:, 0]
        lengths = np.maximum(np.hypot(delta[:, 0], delta[:, 1]), 1e-12)
        segment, frac = samples_along(np.maximum((lengths // spacing_px).astype(int), 1))
        points = model_3d[segment, 0] + frac[:, None] * (model_3d[segment, 1] - model_3d[segment, 0])
        edge, found = evidence.nearest_edges(project_pixels(points, R, t, camera),
                                             evidence.orientation_bin(ends_px)[segment], radius_px)
        if found.sum() < MIN_POLISH_POINTS:
            break
        direction = (delta / lengths[:, None])[segment[found]]
        lines = undistort_segments(np.stack([edge[found] - direction, edge[found] + direction], axis=1), camera)
        R, t = refine_poses(R[None], t[None], points[found][:, None], lines, np.array([0, found.sum()]), f_scale,
                            iterations, weights[segment[found]])
        R, t = R[0], t[0]
    return R, t


#: fewer paired edge points than this do not pin a pose (and suggest a pose off the part)
MIN_POLISH_POINTS = 12


def samples_along(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``counts[i]`` evenly spaced samples on segment i: each sample's segment and its
    fraction along it (the centres of ``counts[i]`` equal pieces)."""
    segment = np.repeat(np.arange(len(counts)), counts)
    offsets = np.arange(len(segment)) - np.repeat(np.cumsum(counts) - counts, counts)
    return segment, (offsets + 0.5) / counts[segment]


class EdgeEvidence:
    """What the image says about edges, prepared once per image for scoring poses.

    Built from the Canny edge pixels, not from the Hough segments: a faint or curved edge
    that the line detector dropped still has its pixels, and a score counted on pixels
    separates right from wrong poses far better (on cluttered renders the true pose scored
    above every wrongly chosen one, where the segment-based score did not).

    * ``support`` (model -> image): share of the projected model edge length within
      ``tolerance`` of an edge pixel of like direction (oriented chamfer: each model point
      looks up the distance to the nearest edge pixel in its direction bin or the two next
      to it).
    * ``explained`` (image -> model): share of the edge pixels inside the projected part's
      convex outline, grown by ``OUTLINE_MARGIN``, lying within ``tolerance`` of a
      projected model edge. The margin, at least ``MIN_MARGIN_PX``, is what stops a small
      pose that fits one inner feature (a window of the part) from explaining everything
      it covers: a relative margin alone grows with the pose, and poses 5x too far away
      that sat on one hole of the part outscored the true pose on clean images (measured
      on bench/accuracy.py scenes: with the floor, 78 instead of 74 of 96 clean images
      succeed, together with 6 hypotheses per region).

    Both run hundreds of times per image and only ask whether a distance is within
    ``tolerance``, so neither computes distances: with OpenCV's 3x3 chamfer distance
    (``cv2.distanceTransform(..., DIST_L2, 3)``, an exact shortest path in integer steps)
    "within r of a set" is the set dilated by the chamfer ball of radius r
    (``chamfer_ball``), several times cheaper than the transform. ``support`` dilates,
    once per tolerance, the edge pixels of each direction bin together with the two next
    to it, so that a model point needs one look-up.
    """

    BINS = 8
    OUTLINE_MARGIN = 0.2
    MIN_MARGIN_PX = 40.0

    def __init__(self, edge_map: np.ndarray, gray: np.ndarray):
        self.shape = edge_map.shape
        self.edges = edge_map > 0
        rows, cols = np.nonzero(self.edges)
        smooth = cv2.GaussianBlur(np.asarray(gray, np.float32), (5, 5), 0)
        dx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0)[rows, cols]
        dy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1)[rows, cols]
        #: the edge pixels (x, y) and the direction each edge runs in, modulo pi (across the
        #: gradient): the pre-filter's picture of an image region
        self.pixels = np.stack([cols, rows], axis=1)
        self.directions = np.mod(np.arctan2(dy, dx) + np.pi / 2, np.pi)
        bins = (self.directions / np.pi * self.BINS).astype(int) % self.BINS
        self._edge_bins = np.zeros(self.shape, np.uint8)
        self._edge_bins[rows, cols] = bins
        #: per direction bin b, the edge pixels of bins b - 1, b and b + 1
        self.like_edges = np.zeros((self.BINS,) + self.shape, np.uint8)
        for step in (-1, 0, 1):
            self.like_edges[(bins + step) % self.BINS, rows, cols] = 1
        self._near_like = {}  # tolerance -> like_edges dilated by its chamfer ball

    def orientation_bin(self, segments: np.ndarray) -> np.ndarray:
        return self._bins_of(segments[:, 1] - segments[:, 0])

    def _bins_of(self, d: np.ndarray) -> np.ndarray:
        return (np.mod(np.arctan2(d[:, 1], d[:, 0]), np.pi) / np.pi * self.BINS).astype(int) % self.BINS

    def support(self, model_px: np.ndarray, tolerance_px: float) -> float:
        return float(self.supports(model_px, np.array([0, len(model_px)]), tolerance_px)[0])

    def supports(self, model_px: np.ndarray, spans: np.ndarray, tolerance_px: float) -> np.ndarray:
        """``support`` of several poses at once, segments ``spans[b]:spans[b + 1]`` of
        ``model_px`` belonging to pose b: the look-ups of all poses run together, each
        pose's sums separately (the same sums as alone)."""
        if tolerance_px not in self._near_like:
            # one pixel of False around the image: points outside it are clipped onto that
            # border instead of being masked out (a mask costs several array operations)
            # (filled in place: np.stack, > 0 and np.pad of the 8 maps took 5 of these 6 ms)
            ball = chamfer_ball(tolerance_px)
            near = np.zeros((self.BINS, self.shape[0] + 2, self.shape[1] + 2), np.uint8)
            for b, like in enumerate(self.like_edges):
                near[b, 1:-1, 1:-1] = cv2.dilate(like, ball)
            self._near_like[tolerance_px] = near.view(bool)  # 0/1 bytes, dilated from 0/1
        h, w = self.shape
        delta = model_px[:, 1] - model_px[:, 0]
        lengths = np.sqrt((delta * delta).sum(axis=1))
        counts = np.clip(np.ceil(lengths / 2.0).astype(int), 1, 2000)
        seg_idx, frac = samples_along(counts)
        pts = model_px[:, 0][seg_idx] + frac[:, None] * delta[seg_idx]
        weight = (lengths / counts)[seg_idx]
        x, y = np.clip(np.rint(pts).astype(int) + 1, 0, [w + 1, h + 1]).T
        near = self._near_like[tolerance_px][self._bins_of(delta)[seg_idx], y, x]
        out = np.zeros(len(spans) - 1)
        point_spans = np.concatenate([[0], np.cumsum(counts)])[spans]
        for b, (lo, hi) in enumerate(zip(point_spans[:-1], point_spans[1:])):
            if hi > lo:
                out[b] = weight[lo:hi][near[lo:hi]].sum() / max(weight[lo:hi].sum(), 1e-12)
        return out

    def nearest_edges(self, points_px: np.ndarray, bins: np.ndarray, radius_px: float) -> tuple[np.ndarray, np.ndarray]:
        """For points (N, 2) on model edges of direction ``bins`` (N,): the nearest edge
        pixel (N, 2), x and y, and whether it lies within ``radius_px`` and runs alike
        (its direction bin within one of the point's). The distance transform covers only
        the points' bounding box (about 1.5 ms for a 200 x 200 pixel part, 10 ms for the
        whole 640 x 480 image)."""
        h, w = self.shape
        pad = int(np.ceil(radius_px)) + 1
        x0, y0 = np.clip(np.floor(points_px.min(axis=0)).astype(int) - pad, 0, [w, h])
        x1, y1 = np.clip(np.ceil(points_px.max(axis=0)).astype(int) + pad + 1, 0, [w, h])
        nearest, found = np.zeros_like(points_px, dtype=float), np.zeros(len(points_px), bool)
        window = self.edges[y0:y1, x0:x1]
        if not window.any():
            return nearest, found
        _, labels = cv2.distanceTransformWithLabels((~window).astype(np.uint8), cv2.DIST_L2, 5,
                                                    labelType=cv2.DIST_LABEL_PIXEL)
        rows, cols = np.nonzero(window)
        pixel_of = np.zeros((labels.max() + 1, 2), np.int64)  # label -> (x, y) of its edge pixel
        pixel_of[labels[rows, cols]] = np.stack([cols, rows], axis=1)
        x, y = np.rint(points_px).astype(int).T
        inside = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
        edge = pixel_of[labels[np.clip(y - y0, 0, y1 - y0 - 1), np.clip(x - x0, 0, x1 - x0 - 1)]] + [x0, y0]
        turn = np.abs(self._edge_bins[edge[:, 1], edge[:, 0]] - bins) % self.BINS
        found = inside & (np.minimum(turn, self.BINS - turn) <= 1) & \
            (np.hypot(*(edge - points_px).T) <= radius_px)
        return edge.astype(float), found

    @classmethod
    def grown_outline(cls, points: np.ndarray) -> np.ndarray:
        """Convex hull of the points, grown about its centre by the margin (class doc)."""
        hull = convex_hull(points)
        center = hull.mean(axis=0)
        radius = max(float(np.sqrt(np.mean(np.sum((hull - center) ** 2, axis=1)))), 1.0)
        return center + (1.0 + max(cls.OUTLINE_MARGIN, cls.MIN_MARGIN_PX / radius)) * (hull - center)

    def explained(self, model_px: np.ndarray, tolerance_px: float) -> float:
        if len(model_px) == 0:
            return 0.0
        h, w = self.shape
        pts = np.clip(np.asarray(model_px, np.float64).reshape(-1, 2), -4.0 * max(h, w), 5.0 * max(h, w))
        hull = self.grown_outline(pts)
        # work in the outline's bounding box only: a part rarely fills the image
        pad = int(np.ceil(tolerance_px)) + 1
        x0, y0 = np.maximum(np.floor(hull.min(axis=0)).astype(int) - pad, 0)
        x1, y1 = np.minimum(np.ceil(hull.max(axis=0)).astype(int) + pad + 1, [w, h])
        if x1 <= x0 or y1 <= y0:
            return 0.0
        offset = np.array([x0, y0])
        outline = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(outline, np.round(hull - offset).astype(np.int32), 1)
        inside = self.edges[y0:y1, x0:x1] & (outline > 0)
        total = np.count_nonzero(inside)
        if total == 0:
            return 0.0
        drawn = np.zeros(outline.shape, np.uint8)
        cv2.polylines(drawn, np.rint(pts.reshape(-1, 2, 2) - offset).astype(np.int32), False, 1, 1)
        near = cv2.dilate(drawn, chamfer_ball(tolerance_px)) > 0
        return float(np.count_nonzero(near & inside) / total)


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Corners (K, 2) of the convex hull of points (..., 2)."""
    return cv2.convexHull(np.asarray(points, np.float32).reshape(-1, 2)).reshape(-1, 2).astype(np.float64)


@lru_cache(maxsize=16)
def chamfer_ball(radius: float) -> np.ndarray:
    """Structuring element of the offsets within ``radius`` (>= 0) of the centre by
    OpenCV's 3x3 L2 chamfer distance.

    That distance is a shortest path of axial and diagonal steps (both at least 0.95
    pixels), so a pixel's distance transform is the smallest chamfer norm of its offset
    to any set pixel, and ``distanceTransform(...) <= radius`` is exactly the set dilated
    by this ball. The ball comes from the same transform, so the two agree to the bit.
    """
    half = int(radius / 0.95) + 1
    canvas = np.full((2 * half + 1, 2 * half + 1), 255, np.uint8)
    canvas[half, half] = 0
    return (cv2.distanceTransform(canvas, cv2.DIST_L2, 3) <= radius).astype(np.uint8)

"""From a matched view to a metric 6-DoF pose, and its refinement.

First pose (what the paper leaves out). A view is an orthographic picture of the part seen
along one direction. An off-centre part is not seen along the optical axis but along the
ray through it, so the image edges of a region are first turned onto a *virtual camera*
whose optical axis is that ray (``camera.virtual_alignment``, ``regions``). There the part
is centred and its image is, to first order, the view scaled by 1/depth.
The similarity (scale k, rotation phi, shift tau) that maps the view's orthographic
coordinates (metres) onto the virtual image (normalised coordinates) then gives

    R = R_align @ Rz(phi) @ R_view,    t = R_align @ ([tau, 1] / k) - R @ c0

with c0 the model centre: depth comes from scale, not from a sampled camera distance.

Refinement. Every matched view segment carries its two 3D end points on the model; every
image segment is a line. A robust Gauss-Newton (Huber weights) over the 6 pose parameters pulls
the projected end points onto their image lines. Between rounds the visible edges of the
graph view nearest to the current pose are projected again and re-associated with the
image lines, with a tolerance that shrinks round by round (the schedules below). A pose
keeps the result of the wide rounds, and then of the rounds at the final tolerance, only if
the score does not drop: from a start that is already near, a wide round pairs the edges
whose own image line is missing with lines of neighbouring objects and pulls the pose onto
them (a scanned part's curved outline gives a handful of lines, and 5 of 7 pairs may be
wrong), and the score, counted on edge pixels, mostly tells that step from a good one
(docs/results/real_lmo.md). Two checks rather than one per round: scoring is most of the
refinement's time.

The chosen pose then climbs over neighbouring views of the graph (``PoseRefiner.climb``)
and is polished on the Canny edge pixels (``polish_pose``), which hear edges the line
detector missed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..aspect_graph import AspectGraph
from ..camera import Camera
from ..geometry import rot_z, rotation_angle_deg, rotation_between
from ..params import PoseParams
from .frame import Frame
from .hypotheses import Hypothesis
from .kernels import refine_poses_kernel, refine_rounds_kernel
from .lines2d import NEAREST_MAX_ANGLE_DEG, cos_deg, line_equations, samples_along
from .scoring import CLEAR_SCORE, EdgeEvidence, pose_scores
from .workers import SERIAL, WorkerPool


#: association tolerances of the wide rounds that start a hypothesis's refinement, in units
#: of pose.inlier_pixels, halving: a first pose lands within several pixels of its lines,
#: and each round's pose is near enough for the next; every further round
#: (``pose.refine_iterations`` in all) is at the final tolerance 1
WIDE_ROUNDS = (8.0, 4.0, 2.0)
#: the rounds of each step of the view climb: a turned pose starts near, so not at the widest
CLIMB_ROUNDS = (4.0, 2.0)
#: the round that settles the climb's result at the final tolerance
SETTLE_ROUNDS = (1.0,)

#: Gauss-Newton steps per round: a wide round only has to bring the pose near enough for
#: the next association, so 3 steps do; the rounds at the final tolerance converge fully
ROUGH_ITERATIONS = 3
FINE_ITERATIONS = 8

#: the polish on edge pixels (``polish_pose``): the line refinement leaves the pose within a
#: few pixels, which 3 rounds of re-pairing (3 Gauss-Newton steps each) close
POLISH_ROUNDS = 3
#: a point every 3 pixels along the model edges: closer points would pair with the same
#: edge pixels and only weigh that stretch of edge more
POLISH_SPACING_PIXELS = 3.0
#: Huber threshold: edge pixels sit on the integer grid, so residuals up to about a pixel
#: are quantisation, not outliers
POLISH_HUBER_PIXELS = 1.0
#: fewer paired edge points than this do not pin a pose (and suggest a pose off the part)
MIN_POLISH_POINTS = 12

#: weight of a model edge in the polish by kind (sharp, outline, smooth): the silhouette of
#: a curved face is a soft edge, whose image lies about 8 times farther from it than from a
#: sharp edge; at 0.3 outlines still pin parts made mostly of them (docs/DECISIONS.md).
#: Smooth edges (graphs compiled with --smooth) share the outlines' weight, unmeasured
POLISH_KIND_WEIGHTS = np.array([1.0, 0.3, 0.3])

#: refined poses closer than this (rotation, and translation in part diameters) are one
#: pose: below the graph's view spacing and well below a success's translation bound
SAME_POSE_DEG = 3.0
SAME_POSE_DIAMETERS = 0.02

#: a view-search step must raise the score by more than this: neighbours that refine back
#: into the same pose differ by 1e-14, and following that noise only costs refinements
CLIMB_MIN_GAIN = 1e-6

#: graph neighbours tried per step of the view search: on the golden-spiral sphere a view's
#: 6 to 8 nearest ring it, so every direction around it is tried
NEIGHBOURS = 8


@dataclass
class Candidate:
    """A refined pose with its score and the hypothesis it grew from."""

    score: float
    R: np.ndarray
    t: np.ndarray
    hypothesis: Hypothesis
    #: (6, 6) of the polished pose (``refine_poses``), None before the polish or if it took no step
    covariance: np.ndarray | None = None


def pose_from_similarity(R_view: np.ndarray, model_center: np.ndarray, *, scale: float, phi: float,
                         shift: np.ndarray, R_align: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """T_cam_model from a view and the similarity view (metres) -> virtual image (module doc)."""
    R = R_align @ rot_z(phi) @ R_view
    center_virtual = np.array([shift[0], shift[1], 1.0]) / scale
    t = R_align @ center_virtual - R @ model_center
    return R, t


#: reorders refine_poses' unknowns (rotation vector, translation) to PoseWithCovariance's
TRANSLATION_FIRST = [3, 4, 5, 0, 1, 2]


def refine_poses(R: np.ndarray, t: np.ndarray, model_3d: np.ndarray, image_2d: np.ndarray, spans: np.ndarray, *,
                 f_scale: float, iterations: int, weights: np.ndarray | None = None,
                 covariance_out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Robust Gauss-Newton on the point-to-line distances (normalised units), for B poses
    R (B, 3, 3), t (B, 3) at once: pairs (model points (K, P, 3), image line) ``spans[b]:spans[b + 1]``
    belong to pose b; the P points of a pair (a segment's 2 end points, or 1 sampled point)
    are pulled onto its line. Returns new arrays.

    Iteratively reweighted least squares with Huber weights (``f_scale`` is the Huber
    threshold) times the pair's ``weights`` (K,) if given (1 by default), an analytic
    Jacobian and the update R <- exp(w) R, t <- t + dt: six unknowns, so each step is a 6x6
    solve per pose; far cheaper than a generic solver with numeric derivatives. It runs for
    every hypothesis and every neighbouring view the climb tries, on about a hundred points
    each, so it is a compiled loop (``kernels.refine_poses_kernel``, numba, GIL released):
    as numpy array operations its per-call overhead was the cost and held the GIL. Each
    pose refines alone, to the same bits alone or in a batch. A pose with fewer than 3
    pairs stays where it is; a pose stops once its step vanishes.

    ``covariance_out`` (B, 6, 6), if given, receives each pose's covariance from its last
    step (left as it is for a pose that took none): ``sigma^2 (J^T W J)^-1`` with the
    weighted residual variance ``sigma^2 = sum(W r^2) / (n - 6)``, ordered translation
    then rotation (x, y, z, then the rotation vector w of R <- exp(w) R), all in the camera
    frame, metres and radians: PoseWithCovariance's order and meaning.
    """
    R, t = np.array(R, dtype=float), np.array(t, dtype=float)
    per_pair = model_3d.shape[1]
    pair_weights = np.ones(len(image_2d)) if weights is None else np.ascontiguousarray(weights, dtype=float)
    normal, variance = np.zeros((len(R), 6, 6)), np.full(len(R), np.nan)
    refine_poses_kernel(R, t, np.ascontiguousarray(model_3d, dtype=float).reshape(-1, 3), line_equations(image_2d),
                        per_pair, pair_weights, per_pair * np.asarray(spans, dtype=np.int64), np.diff(spans) >= 3,
                        float(f_scale), int(iterations), normal, variance)
    if covariance_out is not None:
        for b in np.nonzero(np.isfinite(variance))[0]:
            covariance_out[b] = variance[b] * np.linalg.pinv(normal[b])[TRANSLATION_FIRST][:, TRANSLATION_FIRST]
    return R, t


def polish_pose(R: np.ndarray, t: np.ndarray, model_3d: np.ndarray, *, weights: np.ndarray, evidence: EdgeEvidence,
                camera: Camera, radius_px: float, rounds: int, spacing_px: float, f_scale: float,
                iterations: int, covariance_out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Refine one pose on the Canny edge pixels rather than on the Hough lines.

    Points every ``spacing_px`` along the projected model segments (M, 2, 3) are paired
    with their nearest like-oriented edge pixel within ``radius_px``
    (``EdgeEvidence.nearest_edges``) and pulled onto the line through it along the model
    edge, weighted by ``weights`` (M,) per segment; re-paired each round. Every projected
    edge speaks, where the line refinement only hears edges the line detector found
    (6-12 on the rounded bracket, whose arcs and holes give no Hough lines).
    ``covariance_out`` (1, 6, 6) receives the covariance of the last step (``refine_poses``).
    """
    for _ in range(rounds):
        ends_px = camera.project_model(model_3d, R, t)
        delta = ends_px[:, 1] - ends_px[:, 0]
        lengths = np.maximum(np.hypot(delta[:, 0], delta[:, 1]), 1e-12)
        segment, frac = samples_along(np.maximum((lengths // spacing_px).astype(int), 1))
        points = model_3d[segment, 0] + frac[:, None] * (model_3d[segment, 1] - model_3d[segment, 0])
        edge, found = evidence.nearest_edges(camera.project_model(points, R, t),
                                             evidence.orientation_bin(ends_px)[segment], radius_px)
        if found.sum() < MIN_POLISH_POINTS:
            break
        direction = (delta / lengths[:, None])[segment[found]]
        lines = camera.undistort(np.stack([edge[found] - direction, edge[found] + direction], axis=1))
        R, t = refine_poses(R[None], t[None], points[found][:, None], lines, np.array([0, found.sum()]),
                            f_scale=f_scale, iterations=iterations, weights=weights[segment[found]],
                            covariance_out=covariance_out)
        R, t = R[0], t[0]
    return R, t


def hypothesis_rounds(count: int) -> tuple[float, ...]:
    """The tolerances of ``count`` refinement rounds: the wide ones first, the rest at 1."""
    count = max(count, 0)
    return (WIDE_ROUNDS + (1.0,) * max(count - len(WIDE_ROUNDS), 0))[:count]


class PoseRefiner:
    """Turns hypotheses into refined, scored poses and picks the best (the view climb and
    the polish); ``pose_scores`` is the measure throughout."""

    def __init__(self, graph: AspectGraph):
        self.graph = graph
        self.neighbours = nearest_neighbours(graph.view_directions, NEIGHBOURS)

    def verify(self, hypotheses: list[Hypothesis], frame: Frame, p: PoseParams,
               pool: WorkerPool = SERIAL) -> list[Candidate]:
        """The first poses of the hypotheses, refined together against the image lines, and
        their scores."""
        if not hypotheses:
            return []
        g = self.graph
        first = [pose_from_similarity(g.view_rotations[h.view], g.model_center, scale=h.scale, phi=h.phi,
                                      shift=h.shift, R_align=h.region.R_align) for h in hypotheses]
        R, t, scores = self.refined_scores(np.array([R for R, _ in first]), np.array([t for _, t in first]), frame,
                                           p, hypothesis_rounds(p.refine_iterations), pool)
        return [Candidate(float(scores[j]), R[j], t[j], h) for j, h in enumerate(hypotheses)]

    def refined_scores(self, R: np.ndarray, t: np.ndarray, frame: Frame, p: PoseParams, rounds: tuple[float, ...],
                       pool: WorkerPool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``refine`` and ``pose_scores`` of B poses in two stages, the wide rounds and then
        those at the final tolerance: a pose keeps a stage's result only if it scores no
        lower (module doc). The poses are split between the ``pool``'s threads: each pose
        refines and scores to the same bits alone or in a batch."""
        def chunk(which: slice) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            R_c, t_c = np.array(R[which], dtype=float), np.array(t[which], dtype=float)
            scores = pose_scores(self.graph, R_c, t_c, frame, p)
            for stage in (tuple(f for f in rounds if f > 1), tuple(f for f in rounds if f <= 1)):
                if stage:
                    R_n, t_n = self.refine(R_c, t_c, frame, p, stage)
                    new = pose_scores(self.graph, R_n, t_n, frame, p)
                    kept = new >= scores
                    R_c[kept], t_c[kept], scores[kept] = R_n[kept], t_n[kept], new[kept]
            return R_c, t_c, scores

        parts = pool.map(chunk, pool.split(len(R)))
        return tuple(np.concatenate([part[k] for part in parts]) for k in range(3))

    def best(self, candidates: list[Candidate], frame: Frame, p: PoseParams, pool: WorkerPool = SERIAL) -> Candidate:
        """The best pose of the candidates: the distinct best ones climbed over neighbouring
        views (until one scores ``CLEAR_SCORE``), the winner polished on edge pixels."""
        candidates = sorted(candidates, key=lambda c: -c.score)
        starts = distinct_poses(candidates, p.climb_candidates, self.graph.model_diameter)
        best = self.climb(starts[0], frame, p, pool)
        for start in starts[1:]:
            if best.score >= CLEAR_SCORE:
                break  # no other pose can explain the image much better; save its climb
            climbed = self.climb(start, frame, p, pool)
            best = climbed if climbed.score > best.score else best
        return self.polish(best, frame, p)

    def climb(self, start: Candidate, frame: Frame, p: PoseParams, pool: WorkerPool = SERIAL) -> Candidate:
        """Hill-climb the score over neighbouring views of the aspect graph.

        A hypothesis from a view 10-30 degrees off refines into a nearby local optimum.
        Each step turns the pose so that the camera sees the part along each of the
        current view's graph neighbours (keeping the part's centre where it is), refines
        those turned poses briefly (together: one batch), and moves to the best-scoring
        neighbour while the score improves by more than float noise.
        """
        g, best = self.graph, start
        if start.score >= CLEAR_SCORE:
            return start  # nothing left to find, only the score's noise to chase
        for _ in range(p.view_search_steps):
            here = g.nearest_view(best.R, best.t)
            center = best.R @ g.model_center + best.t
            R = np.array([best.R @ rotation_between(g.view_directions[neighbour], g.view_directions[here])
                          for neighbour in self.neighbours[here]])
            R, t, scores = self.refined_scores(R, center - R @ g.model_center, frame, p, CLIMB_ROUNDS, pool)
            improved = best
            for R_j, t_j, score in zip(R, t, scores):
                if score > improved.score + CLIMB_MIN_GAIN:
                    improved = Candidate(float(score), R_j, t_j, best.hypothesis)
            if improved is best:
                break
            best = improved
        R, t = self.refine(best.R[None], best.t[None], frame, p, SETTLE_ROUNDS)
        score = float(pose_scores(g, R, t, frame, p)[0])
        return Candidate(score, R[0], t[0], best.hypothesis) if score >= best.score else best

    def polish(self, best: Candidate, frame: Frame, p: PoseParams) -> Candidate:
        """The chosen pose refined on edge pixels (``polish_pose``) and scored again."""
        g, segments = self.graph, self.graph.visible_segments(best.R, best.t)
        covariance = np.full((1, 6, 6), np.nan)
        R, t = polish_pose(best.R, best.t, g.seg_3d[segments], weights=POLISH_KIND_WEIGHTS[g.seg_kind[segments]],
                           evidence=frame.evidence, camera=frame.camera, radius_px=p.inlier_pixels,
                           rounds=POLISH_ROUNDS, spacing_px=POLISH_SPACING_PIXELS,
                           f_scale=POLISH_HUBER_PIXELS / frame.camera.focal, iterations=ROUGH_ITERATIONS,
                           covariance_out=covariance)
        return Candidate(float(pose_scores(g, R[None], t[None], frame, p)[0]), R, t, best.hypothesis,
                         covariance[0] if np.isfinite(covariance).all() else None)

    def refine(self, R: np.ndarray, t: np.ndarray, frame: Frame, p: PoseParams,
               rounds: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Re-associate the visible model edges with image lines and refine, one round per
        tolerance of ``rounds`` (units of ``pose.inlier_pixels``), for B poses R (B, 3, 3),
        t (B, 3); returns new arrays. Per pose and round: the graph view nearest to the
        pose, its segments paired with their nearest image lines (``nearest_lines``; the
        frame's ``refine_segments_n``: longer raw pieces than the search's) and
        the Gauss-Newton steps of ``refine_poses``, all in one compiled call
        (``kernels.refine_rounds_kernel``, GIL released): each pose refines alone, to the
        same bits alone or in a batch. A pose behind the camera is left where it is."""
        g = self.graph
        R, t = np.array(R, dtype=float), np.array(t, dtype=float)
        if len(frame.refine_segments_n):
            image = np.ascontiguousarray(frame.refine_segments_n, dtype=float)
            refine_rounds_kernel(R, t, g.view_directions, g.model_center, g.seg_offsets, g.seg_3d, image,
                                 line_equations(image), p.inlier_pixels / frame.camera.focal,
                                 np.asarray(rounds, dtype=float), ROUGH_ITERATIONS, FINE_ITERATIONS,
                                 cos_deg(NEAREST_MAX_ANGLE_DEG))
        return R, t


def nearest_neighbours(directions: np.ndarray, k: int) -> np.ndarray:
    """(V, k) indices of each direction's k nearest other directions (chunked: V can be 10^4)."""
    out = np.empty((len(directions), min(k, len(directions) - 1)), dtype=np.int64)
    for lo in range(0, len(directions), 1024):
        cos = directions[lo:lo + 1024] @ directions.T
        cos[np.arange(len(cos)), np.arange(lo, lo + len(cos))] = -np.inf
        part = np.argpartition(-cos, out.shape[1] - 1, axis=1)[:, : out.shape[1]]
        order = np.argsort(-np.take_along_axis(cos, part, axis=1), axis=1)
        out[lo:lo + 1024] = np.take_along_axis(part, order, axis=1)
    return out


def distinct_poses(candidates: list[Candidate], count: int, diameter: float) -> list[Candidate]:
    """The first ``count`` candidates (best first) that differ from every one kept before.

    Hypotheses from different regions or neighbouring views often refine into the same
    pose; climbing it twice costs time and explores nothing. Two poses are the same when
    they differ by less than ``SAME_POSE_DEG`` and ``SAME_POSE_DIAMETERS`` of the part.
    """
    kept: list[Candidate] = []
    for c in candidates:
        if len(kept) == count:
            break
        if all(rotation_angle_deg(c.R, k.R) >= SAME_POSE_DEG
               or np.linalg.norm(c.t - k.t) >= SAME_POSE_DIAMETERS * diameter for k in kept):
            kept.append(c)
    return kept

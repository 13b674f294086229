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

A hypothesis's first pose is often 5-15 degrees off, farther from many of its image lines
than the wide rounds' pairs reach (16 px). So each hypothesis is also aligned on the Canny
edge pixels first (``align_on_edges``: points along the visible model edges pair with the
nearest edge pixel of like direction within a radius that starts at a fifth of the part's
projected size and halves down to the final tolerance, ``coarse_to_fine_radii``), then
goes through the same guarded rounds, and the aligned end is kept if it scores clearly
higher (``PoseRefiner.realign``; docs/results/refinement.md).

The best few distinct poses then climb over neighbouring views of the graph, in step
(``PoseRefiner.climb_together``); the best climbed is polished on the Canny edge pixels at
the final tolerance and then twice within ``pose.polish_fine_pixels`` (``align_on_edges``,
``polish_radii``), which hear edges the line detector missed, and the polish is kept unless
the score clearly drops. The estimator polishes the other climbed
poses too, as rivals of the best for ``symmetry.check_rivals`` (``PoseRefiner.finalists``).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..aspect_graph import AspectGraph
from ..camera import Camera
from ..geometry import rot_z, rotation_angle_deg, rotation_between
from ..params import PoseParams
from .frame import Frame
from .hypotheses import Hypothesis
from .kernels import align_on_edges_kernel, refine_poses_kernel, refine_rounds_kernel
from .lines2d import NEAREST_MAX_ANGLE_DEG, cos_deg, line_equations
from .scoring import CLEAR_SCORE, pose_scores
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

#: the alignment on edge pixels (``align_on_edges``) that opens a hypothesis's refinement:
#: its first pairing radius is the power of 2 times ``pose.inlier_pixels`` at least this
#: share of the pose's projected diagonal, halving down to ``pose.inlier_pixels``,
#: ``ALIGN_PASSES`` pairings per radius. A start 15 degrees off lies up to about a tenth of
#: the diagonal from its edges; from the truth turned 15 degrees and moved 5 % of the
#: diameter the line rounds alone brought 4 of 72 starts within the success bounds, with
#: this alignment first 47 (one pairing per radius: about 36; docs/results/refinement.md)
ALIGN_FIRST_RADIUS = 0.2
ALIGN_PASSES = 2
#: a hypothesis keeps its aligned end instead of its line end only if it scores this much
#: higher: on the soft outlines of small curved parts the alignment settles the depth too far
#: for a score a little higher (LM-O renders, 32 near starts right after the rounds 50 -> 59 %,
#: main 91 %), while the starts it rescues gain 0.3-0.8 (bench unchanged)
ALIGN_MIN_GAIN = 0.05
#: the polish on edge pixels: the line refinement leaves the pose within a few pixels, which
#: 3 pairings at ``pose.inlier_pixels`` close
POLISH_ROUNDS = 3
#: then this many pairings within ``pose.polish_fine_pixels``
POLISH_FINE_ROUNDS = 2
#: the polish is kept unless the score drops by more than this: a drop that large means it
#: pulled the pose onto soft or biased edges, while a smaller one is the score's pixel noise
#: in depth on a small part, where the polish, not the score, pins the depth (from the truth
#: of 80 bench images: 77 right after the line rounds, 69 after an unguarded polish, 75 with
#: no drop allowed, 73 with 0.02; the small-part test's scene 2, 3 and 3 of 6)
POLISH_SCORE_SLACK = 0.02
#: a point every 3 pixels along the model edges: closer points would pair with the same
#: edge pixels and only weigh that stretch of edge more
EDGE_SPACING_PIXELS = 3.0
#: Gauss-Newton steps per pairing on edge pixels
EDGE_ITERATIONS = 3
#: fewer paired edge points than this do not pin a pose (and suggest a pose off the part)
MIN_EDGE_POINTS = 12

#: weight of a model edge on edge pixels by kind (sharp, outline, smooth): the silhouette of
#: a curved face is a soft edge, whose image lies about 8 times farther from it than from a
#: sharp edge; at 0.3 outlines still pin parts made mostly of them (docs/DECISIONS.md).
#: Smooth edges (graphs compiled with --smooth) share the outlines' weight, unmeasured
EDGE_KIND_WEIGHTS = np.array([1.0, 0.3, 0.3])

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
    #: the score of the hypothesis's first pose, before any refinement (``verify``): the bar
    #: its edge alignment's steps must clear (``realign``); NaN for a pose not straight from one
    first_score: float = np.nan


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
                 f_scale: float | np.ndarray, iterations: int, weights: np.ndarray | None = None,
                 covariance_out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Robust Gauss-Newton on the point-to-line distances (normalised units), for B poses
    R (B, 3, 3), t (B, 3) at once: pairs (model points (K, P, 3), image line) ``spans[b]:spans[b + 1]``
    belong to pose b; the P points of a pair (a segment's 2 end points, or 1 sampled point)
    are pulled onto its line. Returns new arrays.

    Iteratively reweighted least squares with Huber weights (``f_scale`` is the Huber
    threshold, one for all poses or one per pose) times the pair's ``weights`` (K,) if given (1 by default), an analytic
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
                        np.broadcast_to(np.asarray(f_scale, dtype=float), len(R)).copy(), int(iterations), normal,
                        variance)
    if covariance_out is not None:
        _covariances(normal, variance, covariance_out)
    return R, t


def _covariances(normal: np.ndarray, variance: np.ndarray, out: np.ndarray) -> None:
    """``refine_poses``' covariances from the kernels' normal matrices (B, 6, 6) and residual
    variances (B,), into ``out`` (B, 6, 6) where the variance is finite (a pose took a step)."""
    for b in np.nonzero(np.isfinite(variance))[0]:
        out[b] = variance[b] * np.linalg.pinv(normal[b])[TRANSLATION_FIRST][:, TRANSLATION_FIRST]


def align_on_edges(R: np.ndarray, t: np.ndarray, graph: AspectGraph, frame: Frame, *, radii: np.ndarray,
                   covariance_out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Refine B poses R (B, 3, 3), t (B, 3) on the Canny edge pixels rather than on the
    Hough lines: pairing k of pose b within ``radii[b, k]`` pixels (0: pose b skips it);
    returns new arrays.

    Points every ``EDGE_SPACING_PIXELS`` along the model segments visible at the pose are
    paired with their nearest like-oriented edge pixel within the radius
    (``kernels.nearest_like_edge`` on ``EdgeEvidence.nearest_like``) and pulled onto the
    line through it along the model edge (Huber at half the radius: farther pairs are as
    likely wrong), weighted by the segment's kind (``EDGE_KIND_WEIGHTS``);
    ``EDGE_ITERATIONS`` Gauss-Newton steps per pairing. Every projected edge speaks, where
    the line refinement only hears edges the line detector found (6-12 on the rounded
    bracket, whose arcs and holes give no Hough lines). A pose with fewer than
    ``MIN_EDGE_POINTS`` pairs, behind the camera or with a visible edge reaching the
    camera's plane, stops where it is. All in one compiled
    call (``kernels.align_on_edges_kernel``, GIL released), each pose alone: as numpy array
    steps per pairing it was the refinement's largest share and held the GIL.
    ``covariance_out`` (B, 6, 6) receives each pose's covariance of its last step
    (``refine_poses``).
    """
    radii = np.ascontiguousarray(radii, dtype=float)
    camera, nearest = frame.camera, frame.evidence.nearest_like(float(radii.max(initial=0.0)))
    R, t = np.array(R, dtype=float), np.array(t, dtype=float)
    # the 8 coefficients of the rational model, or none for a camera without distortion: the
    # kernel's projections then skip them at once instead of testing 8 zeros at every point
    # (0.9x the kernel's time on the occluded latency images)
    distortion = np.zeros(8 if camera.has_distortion else 0)
    if camera.has_distortion:
        distortion[:len(camera.dist_coeffs)] = camera.dist_coeffs
    normal, variance = np.zeros((len(R), 6, 6)), np.full(len(R), np.nan)
    align_on_edges_kernel(R, t, radii, graph.view_directions, graph.model_center, *graph.view_cells, graph.seg_offsets,
                          graph.seg_3d, graph.seg_kind, EDGE_KIND_WEIGHTS,
                          np.array([camera.fx, camera.fy, camera.cx, camera.cy]), distortion, *nearest,
                          EDGE_SPACING_PIXELS, MIN_EDGE_POINTS, EDGE_ITERATIONS, normal, variance)
    if covariance_out is not None:
        _covariances(normal, variance, covariance_out)
    return R, t


def coarse_to_fine_radii(graph: AspectGraph, R: np.ndarray, t: np.ndarray, camera: Camera,
                         inlier_px: float) -> np.ndarray:
    """(B, K) pairing radii of B starts' edge alignment, pixels: per pose ``inlier_px``
    times the powers of 2 from the one at least ``ALIGN_FIRST_RADIUS`` of the pose's
    projected diagonal down to 1, ``ALIGN_PASSES`` pairings each, the poses' schedules
    ending together (0 where a smaller pose's begins later). Powers of 2 keep the radii
    of a pairing few, so the poses refine in a few calls."""
    halvings = np.zeros(len(R), int)
    for b, view in enumerate(graph.nearest_views(R, t)):
        if (R[b] @ graph.model_center + t[b])[2] > 0:
            ends_px = camera.project_model(graph.seg_3d[graph.view_slice(view)], R[b], t[b]).reshape(-1, 2)
            diagonal = float(np.hypot(*np.ptp(ends_px, axis=0))) if len(ends_px) else 0.0
            halvings[b] = int(np.ceil(np.log2(max(ALIGN_FIRST_RADIUS * diagonal / inlier_px, 1.0))))
    steps = np.arange(halvings.max(initial=0), -1, -1)
    radii = np.where(steps[None] <= halvings[:, None], inlier_px * 2.0 ** steps[None], 0.0)
    return np.repeat(radii, ALIGN_PASSES, axis=1)


def polish_radii(p: PoseParams) -> np.ndarray:
    """The polish's pairing radii, pixels: ``POLISH_ROUNDS`` at ``pose.inlier_pixels``, then
    ``POLISH_FINE_ROUNDS`` at ``pose.polish_fine_pixels`` (0, skipped by the kernel, turns them off)."""
    return np.array([p.inlier_pixels] * POLISH_ROUNDS + [p.polish_fine_pixels] * POLISH_FINE_ROUNDS, float)


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
        #: per view, the turns onto its neighbours (``_turns``), derived when the climb first passes
        self._turns: dict[int, list[np.ndarray]] = {}

    def verify(self, hypotheses: list[Hypothesis], frame: Frame, p: PoseParams,
               pool: WorkerPool = SERIAL) -> list[Candidate]:
        """The first poses of the hypotheses refined against the image lines, and their
        scores (each keeps its first pose's score for ``realign``)."""
        if not hypotheses:
            return []
        R, t, scores, start = self._staged(*self._first_poses(hypotheses), frame, p,
                                           self._line_stages(frame, p, hypothesis_rounds(p.refine_iterations)), pool)
        return [Candidate(float(scores[j]), R[j], t[j], h, first_score=float(start[j]))
                for j, h in enumerate(hypotheses)]

    def realign(self, candidates: list[Candidate], frame: Frame, p: PoseParams,
                pool: WorkerPool = SERIAL) -> list[Candidate]:
        """``verify``'s candidates with their hypotheses' first poses also aligned on the
        edge pixels from wide to fine and then refined on the lines (``aligned_ends``): each
        candidate takes the aligned end where it scores ``ALIGN_MIN_GAIN`` higher than its
        line end. The line ends are ``verify``'s, not refined again."""
        if not candidates:
            return []
        R0, t0 = self._first_poses([c.hypothesis for c in candidates])
        R, t, scores = self.aligned_ends(R0, t0, np.array([c.first_score for c in candidates]),
                                         np.array([c.R for c in candidates]), np.array([c.t for c in candidates]),
                                         np.array([c.score for c in candidates]), frame, p,
                                         hypothesis_rounds(p.refine_iterations), pool)
        return [dataclasses.replace(c, score=float(scores[j]), R=R[j], t=t[j]) for j, c in enumerate(candidates)]

    def refined_scores(self, R: np.ndarray, t: np.ndarray, frame: Frame, p: PoseParams, rounds: tuple[float, ...],
                       pool: WorkerPool, align: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``refine`` and ``pose_scores`` of B poses in two stages, the wide rounds and then
        those at the final tolerance: a pose keeps a stage's result only if it scores no
        lower (module doc). With ``align`` each pose also goes through ``aligned_ends``. The
        poses are split between the ``pool``'s threads: each pose refines and scores to the
        same bits alone or in a batch."""
        R_l, t_l, scores, start = self._staged(R, t, frame, p, self._line_stages(frame, p, rounds), pool)
        if align:
            return self.aligned_ends(R, t, start, R_l, t_l, scores, frame, p, rounds, pool)
        return R_l, t_l, scores

    def aligned_ends(self, R: np.ndarray, t: np.ndarray, start: np.ndarray, R_l: np.ndarray, t_l: np.ndarray,
                     scores: np.ndarray, frame: Frame, p: PoseParams, rounds: tuple[float, ...],
                     pool: WorkerPool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """B poses R, t scoring ``start`` aligned on edge pixels (``align``) and then through
        the line stages of ``refined_scores``, each step kept only if it scores no lower; a
        pose's aligned end replaces its line end R_l, t_l (scoring ``scores``) if it scores
        ``ALIGN_MIN_GAIN`` higher: the alignment brings far starts in, but it can settle a
        near start at the wrong depth where the line rounds alone would not (the sharp
        bracket's clutter image 4: 8 mm deep, docs/results/refinement.md). New arrays."""
        # the alignment's first radii reach a fifth of a pose's size and more: the whole image's
        # nearest-edge table (Frame.detect's reaches the polish), built here over the pool's
        # threads rather than by the first chunk to need it while the others wait
        frame.evidence.nearest_like(pool=pool)
        stages = [lambda R_s, t_s: self.align(R_s, t_s, frame, p)] + self._line_stages(frame, p, rounds)
        R_a, t_a, aligned, _ = self._staged(R, t, frame, p, stages, pool, start)
        better = aligned > scores + ALIGN_MIN_GAIN
        R_l, t_l, scores = R_l.copy(), t_l.copy(), scores.copy()
        R_l[better], t_l[better], scores[better] = R_a[better], t_a[better], aligned[better]
        return R_l, t_l, scores

    def _first_poses(self, hypotheses: list[Hypothesis]) -> tuple[np.ndarray, np.ndarray]:
        """(B, 3, 3), (B, 3): each hypothesis's pose from its view and similarity."""
        g = self.graph
        first = [pose_from_similarity(g.view_rotations[h.view], g.model_center, scale=h.scale, phi=h.phi,
                                      shift=h.shift, R_align=h.region.R_align) for h in hypotheses]
        return np.array([R for R, _ in first]), np.array([t for _, t in first])

    def _line_stages(self, frame: Frame, p: PoseParams, rounds: tuple[float, ...]) -> list:
        """``refine`` as ``_staged``'s stages: the wide rounds of ``rounds``, then those at the final tolerance."""
        return [lambda R_c, t_c, stage=stage: self.refine(R_c, t_c, frame, p, stage)
                for stage in (tuple(f for f in rounds if f > 1), tuple(f for f in rounds if f <= 1)) if stage]

    def _staged(self, R: np.ndarray, t: np.ndarray, frame: Frame, p: PoseParams, stages: list, pool: WorkerPool,
                start: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """B poses through ``stages`` (functions of R, t), a pose keeping a stage's result
        only if it scores no lower: the poses R, t, their scores, and the scores of the
        poses given (``start``, scored here if None). Dealt between the ``pool``'s threads
        (``WorkerPool.deal``: of an occluded image's 118 ms of edge alignment, contiguous halves
        gave one thread 67 ms, dealt 61). A pose that a stage leaves where it was, to the bit,
        keeps its score unscored: the rounds at the final tolerance leave 40-47 % of an occluded
        image's hypotheses where they were (fewer than 3 lines near enough to pair)."""
        def chunk(which: slice) -> tuple[np.ndarray, ...]:
            R_c, t_c = np.array(R[which], dtype=float), np.array(t[which], dtype=float)
            first = pose_scores(self.graph, R_c, t_c, frame, p) if start is None else start[which]
            scores = first.copy()
            for stage in stages:
                R_n, t_n = stage(R_c, t_c)
                moved = (np.any(R_n.view(np.int64) != R_c.view(np.int64), axis=(1, 2))
                         | np.any(t_n.view(np.int64) != t_c.view(np.int64), axis=1))
                new = scores.copy()
                if moved.any():
                    new[moved] = pose_scores(self.graph, R_n[moved], t_n[moved], frame, p)
                kept = new >= scores
                R_c[kept], t_c[kept], scores[kept] = R_n[kept], t_n[kept], new[kept]
            return R_c, t_c, scores, first

        return pool.map_dealt(chunk, len(R))  # R, t, scores, first

    def align(self, R: np.ndarray, t: np.ndarray, frame: Frame, p: PoseParams) -> tuple[np.ndarray, np.ndarray]:
        """B poses (B, 3, 3), (B, 3) aligned on the edge pixels with radii from wide to
        ``pose.inlier_pixels`` (``align_on_edges``, ``coarse_to_fine_radii``); new arrays."""
        return align_on_edges(R, t, self.graph, frame,
                              radii=coarse_to_fine_radii(self.graph, R, t, frame.camera, p.inlier_pixels))

    def best(self, candidates: list[Candidate], frame: Frame, p: PoseParams, pool: WorkerPool = SERIAL,
             climbs: dict | None = None) -> Candidate:
        """The best pose of the candidates: the distinct best ones climbed over neighbouring
        views (until one scores ``CLEAR_SCORE``), the best climbed polished on edge pixels.
        ``climbs`` as ``_climbed``'s."""
        return self.polish(self._climbed(candidates, frame, p, pool, climbs)[0], frame, p)

    def finalists(self, candidates: list[Candidate], frame: Frame, p: PoseParams,
                  pool: WorkerPool = SERIAL, climbs: dict | None = None) -> list[Candidate]:
        """The climbed poses of ``best`` (best climbed first), each polished: the first is
        ``best``'s pose, the others its rivals (``symmetry.check_rivals``). ``climbs`` as
        ``_climbed``'s."""
        return self.polished(self._climbed(candidates, frame, p, pool, climbs), frame, p, pool)

    def _climbed(self, candidates: list[Candidate], frame: Frame, p: PoseParams, pool: WorkerPool,
                 climbs: dict | None = None) -> list[Candidate]:
        """The distinct best candidates climbed (until one scores ``CLEAR_SCORE``), best first.
        ``climbs``, if given, holds the climbs made before on the same image and parameters (by
        the start's id, with the start): a start climbed at an earlier stage is not climbed
        again (on the occluded latency images 15 of 72 climbs were repeats). The new starts
        climb together (``climb_together``)."""
        climbs = {} if climbs is None else climbs
        candidates = sorted(candidates, key=lambda c: -c.score)
        starts = distinct_poses(candidates, p.climb_candidates, self.graph.model_diameter)
        fresh = [start for start in starts if id(start) not in climbs]
        for start, climbed in zip(fresh, self.climb_together(fresh, frame, p, pool)):
            if climbed is not None:  # kept beside its climb, the start's id cannot be reused
                climbs[id(start)] = (start, climbed)
        ends: list[Candidate] = []
        for start in starts:
            ends.append(climbs[id(start)][1])
            if ends[-1].score >= CLEAR_SCORE:
                break  # no other pose can explain the image much better; its climb was saved
        return sorted(ends, key=lambda c: -c.score)  # stable: of equal scores the better start

    def climb(self, start: Candidate, frame: Frame, p: PoseParams, pool: WorkerPool = SERIAL) -> Candidate:
        """``start`` hill-climbed over neighbouring views of the aspect graph (``climb_together``)."""
        return self.climb_together([start], frame, p, pool)[0]

    def climb_together(self, starts: list[Candidate], frame: Frame, p: PoseParams,
                       pool: WorkerPool = SERIAL, each_alone: bool = False) -> list[Candidate | None]:
        """Each start hill-climbed over neighbouring views of the aspect graph, in step with
        the others; None for a start not climbed to the end because a start before it climbed
        to ``CLEAR_SCORE`` (``_climbed`` stops at that one), unless ``each_alone``: then every
        start ends as ``climb`` would end it alone (the twin check's twins, each compared).

        A hypothesis from a view 10-30 degrees off refines into a nearby local optimum.
        Each step turns the pose so that the camera sees the part along each of the
        current view's graph neighbours (keeping the part's centre where it is), refines
        those turned poses briefly, and moves to the best-scoring neighbour while the score
        improves by more than float noise. A climb ends the same alone or beside others
        (each pose refines and scores alone): the steps of all climbs go to the ``pool`` as
        one batch, as do the last rounds that settle them, rather than a start's 8
        neighbours at a time (on the occluded latency images 3-4 starts a stage climbing 1-4
        steps, each then a handful of short calls between the threads).
        """
        g = self.graph
        ends: list[Candidate | None] = list(starts)
        # a start scoring CLEAR_SCORE is not climbed (nothing left to find, only the score's
        # noise to chase), and no start after it is needed
        climbing = []
        for k, start in enumerate(starts):
            if start.score < CLEAR_SCORE:
                climbing.append(k)
            elif not each_alone:
                ends[k + 1:] = [None] * (len(starts) - k - 1)
                break
        settling = list(climbing)
        for _ in range(p.view_search_steps):
            if not climbing:
                break
            turned = [(k, ends[k].R @ turn) for k in climbing for turn in self._turns_at(g.nearest_view(ends[k].R,
                                                                                                     ends[k].t))]
            R = np.array([R_k for _, R_k in turned])
            centers = np.array([ends[k].R @ g.model_center + ends[k].t for k, _ in turned])
            R, t, scores = self.refined_scores(R, centers - R @ g.model_center, frame, p, CLIMB_ROUNDS, pool)
            improved = {k: ends[k] for k in climbing}
            for (k, _), R_j, t_j, score in zip(turned, R, t, scores):
                if score > improved[k].score + CLIMB_MIN_GAIN:
                    improved[k] = Candidate(float(score), R_j, t_j, ends[k].hypothesis)
            climbing = [k for k in climbing if improved[k] is not ends[k]]
            for k in climbing:
                ends[k] = improved[k]
            cleared = [k for k in settling if ends[k].score >= CLEAR_SCORE]
            if cleared and not each_alone:  # the climbs after it are not needed
                climbing = [k for k in climbing if k <= cleared[0]]
                settling = [k for k in settling if k <= cleared[0]]
                ends[cleared[0] + 1:] = [None] * (len(starts) - cleared[0] - 1)
        if settling:
            stage = [lambda R_s, t_s: self.refine(R_s, t_s, frame, p, SETTLE_ROUNDS)]
            R, t, scores, _ = self._staged(np.array([ends[k].R for k in settling]),
                                           np.array([ends[k].t for k in settling]), frame, p, stage, pool,
                                           np.array([ends[k].score for k in settling]))
            for j, k in enumerate(settling):  # the settled pose where it scores no lower
                ends[k] = dataclasses.replace(ends[k], score=float(scores[j]), R=R[j], t=t[j])
        return ends

    def _turns_at(self, view: int) -> list[np.ndarray]:
        """The rotations that turn a pose seen from ``view`` to be seen from each of its
        neighbours: the graph's alone, so kept for every later step and image (each costs
        a dozen small numpy calls, which held the GIL for 3 ms of an occluded image)."""
        if view not in self._turns:
            g = self.graph
            self._turns[view] = [rotation_between(g.view_directions[neighbour], g.view_directions[view])
                                 for neighbour in self.neighbours[view]]
        return self._turns[view]

    def polish(self, best: Candidate, frame: Frame, p: PoseParams) -> Candidate:
        """The chosen pose refined on edge pixels at the final radius (``polished``)."""
        return self.polished([best], frame, p)[0]

    def polished(self, chosen: list[Candidate], frame: Frame, p: PoseParams,
                 pool: WorkerPool = SERIAL) -> list[Candidate]:
        """Each pose refined on edge pixels at the final radius (``align_on_edges``), kept
        unless its score drops by more than ``POLISH_SCORE_SLACK``: on soft outlines (a
        curved part's silhouette under lights near the camera) the edge pixels lie inside
        the geometric outline and pull a right pose too far. The covariance is the polish's
        last step's either way: the two poses lie within a pixel or so. The poses are dealt
        between the ``pool``'s threads; each polishes alone."""
        if not chosen:
            return []

        def chunk(which: slice) -> tuple[np.ndarray, ...]:
            R, t = np.array([c.R for c in chosen[which]]), np.array([c.t for c in chosen[which]])
            covariance = np.full((len(R), 6, 6), np.nan)
            R, t = align_on_edges(R, t, self.graph, frame, radii=np.tile(polish_radii(p), (len(R), 1)),
                                  covariance_out=covariance)
            return R, t, pose_scores(self.graph, R, t, frame, p), covariance

        out = []
        for best, R_k, t_k, score, covariance in zip(chosen, *pool.map_dealt(chunk, len(chosen))):
            kept = Candidate(float(score), R_k, t_k, best.hypothesis) if score >= best.score - POLISH_SCORE_SLACK \
                else best
            out.append(dataclasses.replace(kept, covariance=covariance if np.isfinite(covariance).all() else None))
        return out

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
            refine_rounds_kernel(R, t, g.view_directions, g.model_center, *g.view_cells, g.seg_offsets, g.seg_3d,
                                 image, line_equations(image), p.inlier_pixels / frame.camera.focal,
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

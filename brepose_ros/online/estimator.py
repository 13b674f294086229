"""Stage 6: the online pipeline behind one call: image + intrinsics in, metric 6-DoF pose out.

    image --image_edges--> segments (pixels) + Canny edge pixels
      --undistort--> segments and edge pixels in normalised camera coordinates
      --regions--> whole image and clusters of touching segments
      --virtual camera + metric_space--> a normalised edge set per region
      --chamfer pre-filter on the region's edge pixels--> shortlist of (view, rotation)
      --Kuhn-Munkres + similarity + 2D ICP--> hypotheses ranked by two-way edge coverage
      --pose--> first metric pose per hypothesis --refine--> refined poses, scored on edge pixels
      --hill-climb over neighbouring views--> best pose --polish on edge pixels--> final pose;
      found if its score passes pose.min_score

The whole image is matched and verified first, the clusters only when it holds no pose
scoring ``CLEAR_SCORE``. The (region, view, rotation) jobs run region by region, all jobs
of a region as one batch of array operations (``matching.SegmentBatch``);
``matching.workers`` threads split each region's batch between them. Measured (bench/latency.py, 1,505 views, the other
core busy), 2 threads are still no faster than 1 (matching 38-46 against 33-40 ms per
image): the batched steps are short and most of them hold the GIL; so the default is 1.
"""
from __future__ import annotations

import itertools
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import cv2
import numpy as np

from . import matching, pose
from ..aspect_graph import AspectGraph
from ..camera import Camera
from ..geometry import rotation_angle_deg, rotation_between
from .image_edges import detect_edges
from ..metric_space import outline_normalisation as normalisation_of
from ..metric_space import segment_lengths
from ..params import EstimatorParams


@dataclass
class Estimate:
    """What the estimator found in one image (CONVENTIONS.md pose and metrics).

    ``R``/``t`` are T_cam_model (metres) or None when the part was not found. ``score`` in
    [0, 1] weighs how well projected model edges and image edge pixels explain each other
    (``Estimator._scores``); ``error_ratio`` is the share of the chosen view's model edges
    outside the nearest group of edge pairs at the final pose (CONVENTIONS.md; 0 best,
    1 worst): ``n_matched`` of them found an image line within a loose reach, ``n_nearest``
    lie within ``pose.inlier_pixels`` of it.
    """

    found: bool
    R: np.ndarray | None
    t: np.ndarray | None
    score: float
    error_ratio: float
    view_index: int  # graph view nearest to the final pose
    n_image_segments: int
    n_matched: int
    n_nearest: int
    #: matched pairs for overlays: image segments and the model segments projected with
    #: the final pose, both (K, 2, 2) in pixels
    image_segments: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    model_segments: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    timings: dict[str, float] = field(default_factory=dict)
    matched_view: int = -1  # graph view the bipartite matching chose, before refinement


@dataclass
class Region:
    """Image segments of one candidate region, seen by the virtual camera centred on it."""

    indices: np.ndarray  # into the image's segments
    R_align: np.ndarray
    center: np.ndarray  # normalisation in virtual normalised coordinates
    scale: float
    features: matching.SegmentFeatures
    distance_maps: np.ndarray  # oriented distance maps for the chamfer pre-filter


@dataclass
class Hypothesis:
    """A view matched to a region: the similarity view (metres) -> virtual image (normalised)."""

    region: Region
    view: int
    scale: float
    phi: float
    shift: np.ndarray
    coverage: float  # F-measure of the two-way edge coverage after alignment


@dataclass
class Frame:
    """One image's edges in every form the later stages need."""

    segments_px: np.ndarray
    segments_n: np.ndarray  # undistorted, normalised camera coordinates
    camera: Camera
    evidence: pose.EdgeEvidence
    edge_points_n: np.ndarray  # evidence.pixels, undistorted and normalised

    @classmethod
    def of(cls, segments_px: np.ndarray, edge_map: np.ndarray, gray: np.ndarray, camera: Camera) -> "Frame":
        evidence = pose.EdgeEvidence(edge_map, gray)
        return cls(segments_px, pose.undistort_segments(segments_px, camera), camera, evidence,
                   pose.undistort_points(evidence.pixels, camera))

    @property
    def focal(self) -> float:
        return (self.camera.fx + self.camera.fy) / 2.0

    def pixels_around(self, segments_px: np.ndarray) -> np.ndarray:
        """Mask of the edge pixels inside the segments' convex hull grown by
        ``REGION_GROWTH`` about its centre."""
        hull = pose.convex_hull(segments_px)
        center = hull.mean(axis=0)
        hull = center + REGION_GROWTH * (hull - center)
        x0, y0 = np.floor(hull.min(axis=0)).astype(int)
        x1, y1 = np.ceil(hull.max(axis=0)).astype(int) + 1
        mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(mask, np.round(hull - [x0, y0]).astype(np.int32), 1)
        x, y = self.evidence.pixels[:, 0] - x0, self.evidence.pixels[:, 1] - y0
        inside = (x >= 0) & (x < x1 - x0) & (y >= 0) & (y < y1 - y0)
        inside[inside] = mask[y[inside], x[inside]] > 0
        return inside


@dataclass
class Candidate:
    """A refined pose with its score and the hypothesis it grew from."""

    score: float
    R: np.ndarray
    t: np.ndarray
    hypothesis: Hypothesis


#: how far (in units of pose.inlier_pixels) a model edge may lie from an image line and
#: still count as matched for the error ratio; within 1 unit it is in the nearest group
ERROR_RATIO_REACH = 4.0

#: association tolerances of the refinement rounds, in units of pose.inlier_pixels
REFINE_SCHEDULE = (8.0, 4.0, 2.0, 1.0, 1.0, 1.0)

#: Gauss-Newton steps per round: the wide rounds only need to move the pose near enough for
#: the next association, so 3 steps do (measured: the refinement stage 35 % faster; clean
#: success 78 of 96 images before and after on one set, 73 and 71 of 96 on bench/accuracy.py's,
#: within the noise of single flips); the rounds at the final tolerance converge fully
ROUGH_ITERATIONS = 3
FINE_ITERATIONS = 8

#: the chosen pose is polished on edge pixels (``pose.polish_pose``): rounds of pairing
#: (3 Gauss-Newton steps each), a point every 3 pixels along the model edges, Huber at 1
#: pixel (edge pixels sit on the integer grid). Measured refining the true pose of the 24
#: clean bench images per part, success / median translation error (% of the diameter),
#: Hough lines only -> then polished: rounded bracket 22 -> 23, 1.6 -> 0.7 %; Base
#: attachment 21 -> 23, 1.0 -> 1.0 %; Motor1 holder 20 -> 22, 1.2 -> 1.3 %
POLISH_ROUNDS = 3
POLISH_SPACING_PIXELS = 3.0
POLISH_HUBER_PIXELS = 1.0

#: weight of a model edge in the polish by kind (sharp, outline, smooth). The silhouette of
#: a curved face is a soft edge in the image: where image lines meet the rounded bracket's
#: silhouette at the true pose they lie within +-0.1 px (quartiles) of its sharp edges but
#: +-0.8 px of its outlines. Measured as above, outline weight 1 / 0.3 / 0.1 / 0: rounded
#: bracket 23 / 23 / 23 / 24 of 24, median 0.93 / 0.72 / 0.64 / 0.59 %; Base attachment
#: 22 / 23 / 23 / 23, 1.28 / 0.98 / 0.87 / 0.69 %; but the Motor1 holder, whose edges are
#: mostly outlines, 22 / 22 / 22 / 16, 1.25 / 1.33 / 1.68 / 3.57 %. Smooth edges (only in
#: graphs compiled with --smooth) are softer still; they share the outlines' weight, unmeasured.
POLISH_KIND_WEIGHTS = np.array([1.0, 0.3, 0.3])


class ViewLibrary:
    """Per-view features for matching, computed once from the aspect graph."""

    def __init__(self, graph: AspectGraph, max_segments: int):
        self.normalisation = []
        self.features: list[matching.SegmentFeatures] = []
        for v in range(graph.n_views):
            lo, hi = graph.seg_offsets[v], graph.seg_offsets[v + 1]
            metric = graph.seg_2d[lo:hi] * graph.norm_scales[v] + graph.norm_centers[v]
            metric = metric[matching.longest(metric, max_segments)]
            norm = normalisation_of(metric)
            self.normalisation.append(norm)
            self.features.append(matching.describe(norm.apply(metric)))
        histograms = np.stack([f.orientation_histogram for f in self.features])
        self.orientation_spectra = matching.orientation_spectra(histograms)
        #: matching pads every view's segment set to this size: the largest view's, not
        #: ``max_segments``; the sharp bracket's views have at most 36 segments, and padding
        #: them to 36 instead of 60 takes its matching from 39 to 31 ms per image
        self.pad_size = max(len(f.segments) for f in self.features)
        self.prefilter = matching.ChamferPrefilter(self.features)
        self.neighbours = nearest_neighbours(graph.view_directions, NEIGHBOURS)

    def shortlist(self, region: Region, p) -> list[tuple[int, float]]:
        """The (view, rotation) pairs closest to the region by oriented chamfer distance."""
        phis = matching.rotation_candidates(self.orientation_spectra,
                                            region.features.orientation_histogram, p.rotation_candidates)
        views, which = self.prefilter.shortlist(region.distance_maps, phis, p.shortlist_size)
        return [(int(v), float(phis[v, r])) for v, r in zip(views, which)]


class Estimator:
    """Finds one part (one aspect graph) in images. Thread-safe for one caller at a time."""

    def __init__(self, graph: AspectGraph, params: EstimatorParams | None = None):
        self.graph = graph
        self._params = params or EstimatorParams()
        self._views = ViewLibrary(graph, self._params.matching.max_model_segments)
        self._pool = ThreadPoolExecutor(max_workers=max(1, self._params.matching.workers))

    @property
    def params(self) -> EstimatorParams:
        return self._params

    @params.setter
    def params(self, value: EstimatorParams) -> None:
        """New parameters apply from the next image; view features are rebuilt if needed."""
        old = self._params
        self._params = value
        if value.matching.max_model_segments != old.matching.max_model_segments:
            self._views = ViewLibrary(self.graph, value.matching.max_model_segments)
        if value.matching.workers != old.matching.workers:
            self._pool.shutdown(wait=False)
            self._pool = ThreadPoolExecutor(max_workers=max(1, value.matching.workers))

    def close(self) -> None:
        self._pool.shutdown(wait=True)

    # -- the pipeline ------------------------------------------------------------------
    def estimate(self, image: np.ndarray, camera: Camera) -> Estimate:
        """Find the part in ``image`` (grey or BGR ndarray) seen by ``camera``.

        Raises ValueError for an unusable image (empty, wrong shape or dtype) or an image
        whose size disagrees with the camera's.
        """
        p = self._params
        timings: dict[str, float] = {}
        clock = time.perf_counter()
        if image.ndim < 2 or image.shape[0] != camera.height or image.shape[1] != camera.width:
            raise ValueError(f"image of shape {image.shape} does not fit the camera's "
                             f"{camera.width}x{camera.height}")
        edges = detect_edges(image, p.edges)
        segments_px = edges.segments
        clock = _lap(timings, "edges", clock)
        not_found = Estimate(False, None, None, 0.0, 1.0, -1, len(segments_px), 0, 0, timings=timings)
        if len(segments_px) < MIN_REGION_SEGMENTS:
            return not_found
        frame = Frame.of(segments_px, edges.edge_map, edges.gray, camera)
        groups = self._region_groups(frame)
        candidates = []
        # the whole image first: when it holds a clear pose, the clusters (pieces of the
        # same part, or the part among clutter) cannot add one, and their pre-filter,
        # matching and verification are saved
        for batch in (groups[:1], groups[1:]):
            if not batch or any(c.score >= CLEAR_SCORE for c in candidates):
                break
            regions = [r for r in (self._region(indices, frame) for indices in batch) if r is not None]
            jobs = [(region, view, phi) for region in regions
                    for view, phi in self._views.shortlist(region, p.matching)]
            clock = _lap(timings, "prefilter", clock)
            hypotheses = self._match_all(jobs)
            clock = _lap(timings, "matching", clock)
            if hypotheses:
                candidates += self._verify(best_per_region(hypotheses, p.matching.hypotheses), frame)
            clock = _lap(timings, "refinement", clock)
        if not candidates:
            return not_found
        candidates.sort(key=lambda c: -c.score)
        starts = distinct_poses(candidates, p.pose.climb_candidates, self.graph.model_diameter)
        best = self._climb(starts[0], frame)
        for start in starts[1:]:
            if best.score >= CLEAR_SCORE:
                break  # no other pose can explain the image much better; save its climb
            climbed = self._climb(start, frame)
            best = climbed if climbed.score > best.score else best
        best = self._polish(best, frame)
        clock = _lap(timings, "refinement", clock)
        timings["total"] = sum(timings.values())
        found = best.score >= p.pose.min_score
        # the paper's pairs at the final pose: the chosen view's visible model edges matched
        # to image lines within a loose tolerance; the nearest group lies within inlier_pixels
        # (edges that project shorter than the line detector's minimum length cannot be found
        # in any image and are left out)
        visible = self.graph.seg_3d[self._visible_segments(best.R, best.t)]
        lengths = np.linalg.norm(np.diff(pose.project_pixels(visible, best.R, best.t, camera), axis=1), axis=2)[:, 0]
        visible = visible[lengths >= p.edges.min_length_fraction * np.hypot(camera.width, camera.height)]
        tolerance = p.pose.inlier_pixels / frame.focal
        pairs = pose.associate(visible, best.R, best.t, frame.segments_n, ERROR_RATIO_REACH * tolerance)
        nearest = pairs.distances <= tolerance
        error_ratio = 1.0 - float(nearest.sum()) / max(len(visible), 1)
        return Estimate(found, best.R if found else None, best.t if found else None, best.score, error_ratio,
                        self._nearest_view(best.R, best.t), len(segments_px), len(pairs.model_index),
                        int(nearest.sum()), segments_px[pairs.image_index[nearest]],
                        pose.project_pixels(pairs.model_3d[nearest], best.R, best.t, camera), timings,
                        int(best.hypothesis.view))

    def _region_groups(self, frame: Frame) -> list[np.ndarray]:
        """Segment indices of the candidate regions: the whole image, then clusters of
        touching segments (off-centre part among clutter)."""
        groups = [np.arange(len(frame.segments_px))]
        groups += cluster_segments(frame.segments_px, gap=0.03 * np.hypot(frame.camera.width, frame.camera.height))
        return [g for g in groups[: self._params.matching.max_regions] if len(g) >= MIN_REGION_SEGMENTS]

    def _region(self, indices: np.ndarray, frame: Frame) -> Region | None:
        """The region's segments on the virtual camera centred on them, normalised; and the
        pre-filter's distance maps of the edge pixels around them, normalised alike."""
        p = self._params.matching
        indices = indices[matching.longest(frame.segments_n[indices], p.max_image_segments)]
        try:
            center = normalisation_of(frame.segments_n[indices]).center
            R_align = pose.virtual_alignment(center)
            virtual = pose.to_virtual(frame.segments_n[indices], R_align)
            norm = normalisation_of(virtual)
        except ValueError:
            return None
        features = matching.describe(norm.apply(virtual))
        around = frame.pixels_around(frame.segments_px[indices])
        pixels = norm.apply(pose.to_virtual(frame.edge_points_n[around], R_align))
        return Region(indices, R_align, norm.center, norm.scale, features,
                      self._views.prefilter.distance_maps(pixels, frame.evidence.directions[around]))

    def _match_all(self, jobs: list[tuple[Region, int, float]]) -> list[Hypothesis]:
        """Hypotheses of the jobs, in job order. Consecutive jobs of one region run together
        (``_match_batch``), split into one batch per thread."""
        workers = max(1, self._params.matching.workers)
        batches = []
        for _, run in itertools.groupby(jobs, key=lambda job: id(job[0])):
            run = list(run)
            size = -(-len(run) // workers)
            batches += [run[i:i + size] for i in range(0, len(run), size)]
        return [h for batch in self._pool.map(self._match_batch, batches) for h in batch]

    def _match_batch(self, jobs: list[tuple[Region, int, float]]) -> list[Hypothesis]:
        """Kuhn-Munkres at each shortlisted rotation, the similarity its nearest pairs imply,
        then that similarity polished by 2D ICP against the region's lines: for jobs of one
        region at once (``matching.SegmentBatch``); jobs whose pairs give no similarity drop out."""
        p = self._params.matching
        region, image = jobs[0][0], jobs[0][0].features
        views = np.array([view for _, view, _ in jobs])
        phi = np.array([phi for _, _, phi in jobs])
        model = matching.SegmentBatch.pad([self._views.features[v].segments for v in views], self._views.pad_size)
        best = matching.assign(model, image, phi, p)
        similarity = matching.similarity_from_pairs(model, image, best, phi)
        found = np.nonzero(similarity.found)[0]
        if len(found) == 0:
            return []
        model, best, similarity, views = (matching.take(model, found), matching.take(best, found),
                                          matching.take(similarity, found), views[found])
        # re-match with the similarity applied: the pairs now say what is really aligned
        moved = matching.apply_similarity(model.segments, similarity.scale, similarity.angle, similarity.shift)
        refined = matching.assign(matching.SegmentBatch.of(moved, model.valid), image, np.zeros(len(views)), p)
        better = matching.similarity_from_pairs(model, image, refined, similarity.angle)
        switch = (refined.cost < best.cost) & better.found
        for name in ("scale", "angle", "shift"):
            getattr(similarity, name)[switch] = getattr(better, name)[switch]
        a, angle, b = similarity.scale, similarity.angle, similarity.shift
        moved = matching.apply_similarity(model.segments, a, angle, b)
        tolerance = p.coverage_tolerance
        moved, polish = matching.align_to_lines(moved, model.valid, image.segments, (3 * tolerance, tolerance))
        A = polish[:, :, :2] @ (a[:, None, None] * matching.rotations(angle))
        b = np.einsum("jkl,jl->jk", polish[:, :, :2], b) + polish[:, :, 2]
        a, angle = np.sqrt(np.abs(np.linalg.det(A))), np.arctan2(A[:, 1, 0], A[:, 0, 0])
        covered_model, covered_image = matching.coverage(moved, model.valid, image.segments, tolerance)
        f_measure = 2 * covered_model * covered_image / np.maximum(covered_model + covered_image, 1e-12)
        # compose: view metres -> view normalised -> region normalised -> virtual image
        norm_v = [self._views.normalisation[v] for v in views]
        scale = region.scale * a / np.array([n.scale for n in norm_v])
        turned = np.einsum("jkl,jl->jk", matching.rotations(angle), np.array([n.center for n in norm_v]))
        shift = region.center + region.scale * b - scale[:, None] * turned
        return [Hypothesis(region, int(views[j]), float(scale[j]), float(angle[j]), shift[j], float(f_measure[j]))
                for j in range(len(views))]

    def _verify(self, hypotheses: list[Hypothesis], frame: "Frame") -> list["Candidate"]:
        """The first poses of the hypotheses, refined together against the image lines, and
        their scores."""
        g = self.graph
        first = [pose.pose_from_similarity(g.view_rotations[h.view], g.model_center, h.scale, h.phi, h.shift,
                                           h.region.R_align) for h in hypotheses]
        R, t = self._refine(np.array([R for R, _ in first]), np.array([t for _, t in first]), frame,
                            REFINE_SCHEDULE[: self._params.pose.refine_iterations])
        scores = self._scores(R, t, frame)
        return [Candidate(float(scores[j]), R[j], t[j], h) for j, h in enumerate(hypotheses)]

    def _climb(self, start: "Candidate", frame: "Frame") -> "Candidate":
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
        for _ in range(self._params.pose.view_search_steps):
            here = self._nearest_view(best.R, best.t)
            center = best.R @ g.model_center + best.t
            R = np.array([best.R @ rotation_between(g.view_directions[neighbour], g.view_directions[here])
                          for neighbour in self._views.neighbours[here]])
            R, t = self._refine(R, center - R @ g.model_center, frame, REFINE_SCHEDULE[1:3])
            improved = best
            for R_j, t_j, score in zip(R, t, self._scores(R, t, frame)):
                if score > improved.score + CLIMB_MIN_GAIN:
                    improved = Candidate(float(score), R_j, t_j, best.hypothesis)
            if improved is best:
                break
            best = improved
        R, t = self._refine(best.R[None], best.t[None], frame, REFINE_SCHEDULE[3:4])
        score = float(self._scores(R, t, frame)[0])
        return Candidate(score, R[0], t[0], best.hypothesis) if score >= best.score else best

    def _polish(self, best: "Candidate", frame: "Frame") -> "Candidate":
        """The chosen pose refined on edge pixels (``pose.polish_pose``) and scored again."""
        g, segments = self.graph, self._visible_segments(best.R, best.t)
        R, t = pose.polish_pose(best.R, best.t, g.seg_3d[segments], POLISH_KIND_WEIGHTS[g.seg_kind[segments]],
                                frame.evidence, frame.camera, self._params.pose.inlier_pixels, POLISH_ROUNDS,
                                POLISH_SPACING_PIXELS, POLISH_HUBER_PIXELS / frame.focal, ROUGH_ITERATIONS)
        return Candidate(float(self._scores(R[None], t[None], frame)[0]), R, t, best.hypothesis)

    def _refine(self, R: np.ndarray, t: np.ndarray, frame: "Frame", schedule) -> tuple[np.ndarray, np.ndarray]:
        """Re-associate the visible model edges with image lines and refine, round by round,
        for B poses R (B, 3, 3), t (B, 3) at once (``pose.refine_poses``: per-call overhead,
        not arithmetic, is the cost). A pose behind the camera is left where it is."""
        g, tolerance = self.graph, self._params.pose.inlier_pixels / frame.focal
        R, t = np.array(R, dtype=float), np.array(t, dtype=float)
        live = np.ones(len(R), bool)
        for factor in schedule:
            live &= t[:, 2] > 0
            which = np.nonzero(live)[0]
            if len(which) == 0:
                break
            views = self._nearest_views(R[which], t[which])
            lo, counts = g.seg_offsets[views], g.seg_offsets[views + 1] - g.seg_offsets[views]
            spans = np.concatenate([[0], np.cumsum(counts)])
            model_3d = g.seg_3d[np.arange(spans[-1]) - np.repeat(spans[:-1] - lo, counts)]
            mi, ii, _ = pose.associate_poses(model_3d, spans, R[which], t[which], frame.segments_n, factor * tolerance)
            pairs = np.searchsorted(mi, spans)  # mi ascends, so each pose's pairs are one span
            R[which], t[which] = pose.refine_poses(R[which], t[which], model_3d[mi], frame.segments_n[ii], pairs,
                                                   tolerance, ROUGH_ITERATIONS if factor > 1 else FINE_ITERATIONS)
        return R, t

    def _scores(self, R: np.ndarray, t: np.ndarray, frame: "Frame") -> np.ndarray:
        """For B poses (B, 3, 3), (B, 3): F-measure of two shares on the image's edge pixels
        (``pose.EdgeEvidence``; the first share of all poses in one call).

        Of the projected visible model edges, the share an image edge confirms; of the
        image edges inside the projected part's outline, the share a model edge explains.
        Either alone is fooled: a pose far away projects small onto dense edges, a pose too
        close covers every edge in the image; and a pose projecting smaller than
        ``pose.min_size_pixels`` scores 0. Neither share depends on the region a
        hypothesis came from, so hypotheses of all regions compare.
        """
        scored, drawn = [], []
        g = self.graph
        for b, view in enumerate(self._nearest_views(R, t)):
            if t[b][2] <= 0:
                continue
            model_px = pose.project_pixels(g.seg_3d[g.seg_offsets[view]:g.seg_offsets[view + 1]], R[b], t[b],
                                           frame.camera)
            extent = np.ptp(model_px.reshape(-1, 2), axis=0) if len(model_px) else np.zeros(2)
            if np.hypot(*extent) < self._params.pose.min_size_pixels:
                continue  # a part this small is not recognisable, and a tiny pose fits any edges
            scored.append(b)
            drawn.append(model_px)
        scores = np.zeros(len(R))
        if not scored:
            return scores
        tolerance = self._params.pose.inlier_pixels
        spans = np.cumsum([0] + [len(m) for m in drawn])
        confirmed = frame.evidence.supports(np.concatenate(drawn), spans, tolerance)
        for b, c, model_px in zip(scored, confirmed, drawn):
            explained = frame.evidence.explained(model_px, tolerance)
            scores[b] = 2 * c * explained / max(c + explained, 1e-12)
        return scores

    def _nearest_view(self, R: np.ndarray, t: np.ndarray) -> int:
        """The graph view nearest to the direction the camera sees the part from."""
        return int(self._nearest_views(R[None], t[None])[0])

    def _nearest_views(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``_nearest_view`` of B poses (B, 3, 3), (B, 3): ``geometry.direction_to``
        without its normalisation, which cannot change the largest product."""
        g = self.graph
        return np.argmax(g.view_directions @ (g.model_center + np.einsum("bji,bj->bi", R, t)).T, axis=0)

    def _visible_segments(self, R: np.ndarray, t: np.ndarray) -> slice:
        """Segments visible from the graph view nearest to the pose's viewing direction."""
        view = self._nearest_view(R, t)
        return slice(self.graph.seg_offsets[view], self.graph.seg_offsets[view + 1])


#: fewer segments than this cannot pin down a view, in a region or in a whole image
MIN_REGION_SEGMENTS = 4

#: a region's edge pixels are those inside the convex hull of its segments grown by this
#: factor: rounded outlines and corners, which give no segment, bulge out of that hull
REGION_GROWTH = 1.15

#: refined poses closer than this (rotation, and translation in part diameters) are one pose
SAME_POSE_DEG = 3.0
SAME_POSE_DIAMETERS = 0.02

#: a view-search step must raise the score by more than this: neighbours that refine back
#: into the same pose differ by 1e-14, and following that noise only costs refinements
CLIMB_MIN_GAIN = 1e-6

#: a pose scoring this high is not searched further: it is not climbed, nor is any other
#: start once a climb reaches it. On the clean bench images no other start has beaten such a
#: pose (same 73 of 96 successes with and without the second climb). Climbing a start that
#: already scored this high changed no success on bench/accuracy.py's 288 clean, clutter
#: and occl30 images. It moved 11 poses, chasing the score's pixel noise (before the polish
#: on edge pixels by up to 0.7 degrees, 7 of them away from the truth; with the polish, not
#: climbing changes their rotation errors by at most 0.35 degrees, 5 down and 6 up), and
#: cost 12-40 ms each: without it the refinement takes 37 instead of 52 ms CPU per image
#: (median, 2,500-view latency images). Nor are the clusters matched once the whole image
#: holds such a pose: no final pose changed on the 480 images of bench/accuracy.py (all five
#: conditions), and on the latency images whose part falls apart into two clusters a third
#: of the work is saved (69 instead of 114 ms CPU per image, median of all 12)
CLEAR_SCORE = 0.95

#: graph neighbours tried per step of the view search
NEIGHBOURS = 8


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


def best_per_region(hypotheses: list[Hypothesis], count: int) -> list[Hypothesis]:
    """The ``count`` best-covered hypotheses of every region: a small region (the part
    among clutter) must not lose its candidates to the whole image's."""
    chosen = []
    for region_id in {id(h.region) for h in hypotheses}:
        own = [h for h in hypotheses if id(h.region) == region_id]
        chosen += sorted(own, key=lambda h: -h.coverage)[:count]
    return chosen


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


def cluster_segments(segments_px: np.ndarray, gap: float) -> list[np.ndarray]:
    """Groups of segments chained by end points closer than ``gap``, largest first.

    Only groups with at least a tenth of the largest group's total length are returned:
    these are the candidate positions of an off-centre part among clutter.
    """
    n = len(segments_px)
    ends = segments_px.reshape(-1, 2)
    close = np.linalg.norm(ends[:, None] - ends[None, :], axis=2) < gap
    linked = close.reshape(n, 2, n, 2).any(axis=(1, 3))
    parent = np.arange(n)

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(*np.nonzero(np.triu(linked, 1))):
        ri, rj = root(i), root(j)
        if ri != rj:
            parent[ri] = rj
    labels = np.array([root(i) for i in range(n)])
    lengths = segment_lengths(segments_px)
    groups = [np.nonzero(labels == lab)[0] for lab in np.unique(labels)]
    totals = np.array([lengths[g].sum() for g in groups])
    order = np.argsort(-totals)
    keep = [groups[i] for i in order if totals[i] >= 0.1 * totals[order[0]]]
    return keep if len(keep) > 1 else []  # one cluster is the whole image again


def _lap(timings: dict, name: str, start: float) -> float:
    """Add the time since ``start`` to stage ``name`` (a stage may run more than once)."""
    now = time.perf_counter()
    timings[name] = timings.get(name, 0.0) + now - start
    return now

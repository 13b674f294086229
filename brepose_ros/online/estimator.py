"""The online pipeline behind one call: image + intrinsics in, metric 6-DoF pose out.

Each stage lives in its own module; this one only wires them:

1. ``image_edges``: line segments (pixels) and Canny edge pixels, only those within the
   part's colour regions when its model has colour (``colour_regions``); ``frame``: both
   undistorted into normalised camera coordinates, the edge pixels prepared for scoring
   (beside the segments, on the worker threads); once per image for several parts
   (``detect``)
2. ``regions``: the whole image and clusters of touching segments, each seen by its
   virtual camera and normalised like the views
3. hypothesis generators (``search.generators``, one or more, in order): ``tetrad``
   (``hypotheses``): per region, the chamfer pre-filter's (view, rotation) shortlist
   (``prefilter``), then Kuhn-Munkres, similarity and 2D ICP (``matching``): hypotheses
   ranked by two-way edge coverage; ``search``: templates of the views slid over the
   image's gradient directions, no region normalised; ``seeded``: the search's best
   templates each matched by Kuhn-Munkres to the segments around it, normalised in the
   template's own frame (``TetradHypotheses.at_seeds``); ``windows``: the tetrad generator
   on windows about the search's best places instead of the whole image and clusters;
   ``small`` (``small``): templates smaller than the search's, slid only over patches of
   edges that narrow, seeding the matching as ``seeded`` does
4. ``refinement``: a first metric pose per hypothesis, refined on the image lines and
   scored on the edge pixels (``scoring``); the best few climbed over neighbouring views and
   polished on the edge pixels (the finalists), of which ``symmetry.check_rivals`` keeps the
   best climbed or a near tie that the edges telling the two apart show by more; where the
   part's colour regions split into places, steps 1-4 again within each of the few holding
   the most of its colour alone (``colour_regions.colour_places``), a pose found there kept
   if it scores more on the whole regions' edges
5. ``larger``: a pose scoring below ``search.enough_score`` against larger poses about its
   place, searched again (``pose.larger_check``)
6. ``symmetry``: the pose against its twins under the part's near symmetries, on the
   edges that tell them apart; ambiguous when the image cannot decide
7. ``scoring``: the error ratio and the score's shares at the pose; ``appearance``: the
   shading fit over its silhouette where the graph holds the part's surface;
   ``confidence``: from both, the probability that the pose is right where the part is in
   view in a share ``pose.prior`` of the images; found (``is_found``) if the score passes
   its floor ``pose.min_score`` and the confidence ``pose.min_confidence`` and its model
   centre lies within the working range
   ``pose.min_distance`` - ``pose.max_distance`` (when given; the search then tries only the
   part's sizes in that range, and the candidates and finalists outside it are dropped)

``estimate(..., paper_only=True)`` stops after step 3, as the seed paper does (section 6):
the bipartite matching's best-covered hypothesis over all regions, its view turned into a
pose by the similarity alone (``refinement.pose_from_similarity``), not refined nor
verified; the paper has no "not found", so any hypothesis is reported. It is the
baseline of bench/paper_figures.py and of the learning (brepose-learn).

The generators run in the order named; a later one only while the best pose so far,
climbed and polished, scores below ``search.enough_score``. The tetrad generator matches
and verifies the whole image, then the clusters only when no pose so far scores
``scoring.CLEAR_SCORE``. With ``search.time_budget_ms`` a later generator, a colour place
and the larger check start only if they still fit before the image's deadline, judged on
what they took on this estimator's recent images (``time_budget``): a cell that needs an
answer in time gets the best pose of what ran, and the estimate names the rest.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from ..aspect_graph import AspectGraph
from ..camera import Camera
from ..params import EstimatorParams, PoseParams, SearchParams
from .frame import Frame
from .hypotheses import TetradHypotheses, best_covered, best_per_region
from .larger import centre_distance, larger_check_applies, larger_pose, projected_place
from . import kernels
from .refinement import Candidate, PoseRefiner, pose_from_similarity
from .regions import MIN_REGION_SEGMENTS, normalised_region, region_groups, segments_within
from .appearance import shading_fit
from .colour_regions import colour_places, colour_regions
from .confidence import Calibration, load_calibration
from .scoring import CLEAR_SCORE, Shares, edge_pairs, pose_scores, pose_shares, scored_tolerances
from .search import TemplateSearch
from .small import small_part_seeds
from .symmetry import check_rivals, check_twins
from .time_budget import LARGER_CHECK, StepCosts, TimeBudget
from .workers import WorkerPool, keep_freed_memory, resolve_workers


@dataclass
class Estimate:
    """What the estimator found in one image (CONVENTIONS.md pose and metrics).

    ``R``/``t`` are T_cam_model (metres) or None when the part was not found. ``score`` in
    [0, 1] weighs how well projected model edges and image edge pixels explain each other
    (``scoring.pose_scores``); ``error_ratio`` is the share of the chosen view's model edges
    outside the nearest group of edge pairs at the final pose (CONVENTIONS.md; 0 best,
    1 worst): ``n_matched`` of them found an image line within a loose reach, ``n_nearest``
    lie within ``pose.inlier_pixels`` of it (``scoring.edge_pairs``).
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
    #: (6, 6) covariance of the pose, x y z then rotations about x y z in the camera frame
    #: (metres, radians): the polish's last Gauss-Newton normal matrix scaled by its residual
    #: variance (``refinement.refine_poses``); None when not found or the polish took no step
    covariance: np.ndarray | None = None
    #: evidence of the pose over its twins under the part's near symmetries, 0 to 1
    #: (``symmetry.check_twins``); None when the part has none or the check is off
    symmetry_margin: float | None = None
    #: the margin is below ``pose.twin_margin``: the image cannot tell the pose from a twin
    ambiguous: bool = False
    #: a twin the image does not tell from the pose scores as well, or a small roll about a near
    #: continuous axis does (``symmetry.Verdict``): which is reported is a coin toss, and the
    #: confidence says so (``confidence.COIN_TOSS``)
    twin_tie: bool = False
    #: the three parts of the score at the final pose (``scoring.Shares``); None when nothing was scored
    shares: Shares | None = None
    #: diagonal and edge length of the projected visible model edges at the final pose, pixels
    size_pixels: float = 0.0
    model_length_pixels: float = 0.0
    #: the probability that the pose is right (``confidence.Calibration``); 0 when no pose was
    #: verified (no candidate, or ``paper_only``)
    confidence: float = 0.0
    #: how far the final pose's model centre lies from the camera, metres (also when not found);
    #: 0 when no pose was verified
    distance: float = 0.0
    #: the steps not started because they would have overrun the image's time budget
    #: (``time_budget.TimeBudget``)
    skipped: tuple[str, ...] = ()
    #: how much of the grey level over the part's silhouette at the pose its surface explains
    #: (``appearance.shading_fit``), a feature of the confidence; None where the aspect graph
    #: holds no surface (compiled before session 27) or no pose was verified
    shading_fit: float | None = None


@dataclass
class ImageWork:
    """One image's estimate as its stages share it: the estimator's parts as they were when it
    started (a parameter change meanwhile applies from the next image), its time budget, and
    the seconds of its stages, each ``lap`` timed from the one before."""

    p: EstimatorParams
    hypotheses: TetradHypotheses
    search: TemplateSearch | None
    pool: WorkerPool
    calibration: Calibration
    budget: TimeBudget
    timings: dict[str, float]
    clock: float = field(default_factory=time.perf_counter)

    def lap(self, stage: str) -> None:
        """Add the time since the last lap (or the start) to ``stage`` (a stage may run more than once)."""
        now = time.perf_counter()
        self.timings[stage] = self.timings.get(stage, 0.0) + now - self.clock
        self.clock = now


class Estimator:
    """Finds one part (one aspect graph) in images, one image at a time: ``estimate`` must
    not run in two threads at once (the ROS node gives each part its own estimator).
    ``params`` may be set from any thread at any time: an image in flight finishes with the
    parameters, views and worker threads it started with."""

    def __init__(self, graph: AspectGraph, params: EstimatorParams | None = None):
        self.graph = graph
        kernels.warm_up()  # compiled (or loaded from numba's cache) now, not on the first image
        graph.view_cells  # the nearest views' look-up derived now too (10 ms at 2,500 views)
        keep_freed_memory()
        self._params = params or EstimatorParams()
        self._check_surface(self._params)
        self._hypotheses = TetradHypotheses(graph, self._params.matching)
        self._refiner = PoseRefiner(graph)
        self._pool = WorkerPool(self._params.matching.workers)
        Frame.warm_up(self._params.edges, self._pool, scored_tolerances(graph, self._params.pose))
        #: pools replaced by a parameter change, closed once no image uses them
        self._retired: list[WorkerPool] = []
        self._lock = threading.Lock()
        self._search = template_search(graph, self._params.search)
        self._calibration = load_calibration(self._params.pose.confidence_file)
        self._step_costs = StepCosts()

    @property
    def params(self) -> EstimatorParams:
        return self._params

    @params.setter
    def params(self, value: EstimatorParams) -> None:
        """New parameters apply from the next image; view features, templates and worker
        threads are rebuilt if needed (never torn down under an image in flight)."""
        calibration = load_calibration(value.pose.confidence_file)  # a bad file refuses the whole change
        self._check_surface(value)
        with self._lock:
            if value.matching.max_model_segments != self._params.matching.max_model_segments:
                self._hypotheses = TetradHypotheses(self.graph, value.matching)
            if self._search is None or TemplateSearch.library_changes(self._params.search, value.search):
                self._search = template_search(self.graph, value.search)
            if resolve_workers(value.matching.workers) != self._pool.size:
                self._retired.append(self._pool)
                self._pool = WorkerPool(value.matching.workers)
            self._params, self._calibration = value, calibration

    def _check_surface(self, params: EstimatorParams) -> None:
        """ValueError where ``pose.min_shading_fit`` asks for the part's surface and the graph
        has none."""
        if params.pose.min_shading_fit > 0 and self.graph.surface is None:
            raise ValueError("pose.min_shading_fit needs the part's surface, which this aspect graph does not "
                             "hold (compiled before session 27): recompile it with brepose-compile, or set 0")

    def close(self) -> None:
        with self._lock:
            pools, self._retired = [self._pool, *self._retired], []
        for pool in pools:
            pool.close()

    def detect(self, image: np.ndarray, camera: Camera, others: Sequence["Estimator"] = ()) -> Frame:
        """The image's edges in every form the stages need (``Frame.detect``) on this estimator's
        threads, for ``estimate(..., frame=)`` of this estimator and of the ``others`` (which
        must have the same edge parameters: the node's parts): with several parts in one
        process, the edges, the largest stage of a clean image, are found once, not per part.
        The evidence's maps are built at every estimator's score tolerances."""
        with self._lock:
            p, pool = self._params, self._pool
        tolerances = tuple(dict.fromkeys(t for e in (self, *others) for t in scored_tolerances(e.graph, e.params.pose)))
        return Frame.detect(image, camera, p.edges, pool, tolerances)[1]

    def estimate(self, image: np.ndarray, camera: Camera, paper_only: bool = False,
                 frame: Frame | None = None) -> Estimate:
        """Find the part in ``image`` (grey or BGR ndarray) seen by ``camera``; with
        ``paper_only`` by the seed paper's method alone (module doc). ``frame``: the image's
        edges from ``detect`` (of this estimator or another with the same edge parameters),
        else they are detected here (timed as the stage ``edges``); also when the part's colour
        regions apply (``part_frame``), whose edges are this part's alone.

        Raises ValueError for an unusable image (empty, wrong shape or dtype) or an image
        whose size disagrees with the camera's.
        """
        work = self._image_work()
        p = work.p
        if image.ndim < 2 or image.shape[0] != camera.height or image.shape[1] != camera.width:
            raise ValueError(f"image of shape {image.shape} does not fit the camera's "
                             f"{camera.width}x{camera.height}")
        regions = self._colour_regions(image, p)
        if frame is None or regions is not None:
            frame = Frame.detect(image, camera, p.edges, work.pool, scored_tolerances(self.graph, p.pose), regions)[1]
            work.lap("edges")
        not_found = Estimate(found=False, R=None, t=None, score=0.0, error_ratio=1.0, view_index=-1,
                             n_image_segments=len(frame.segments_px), n_matched=0, n_nearest=0, timings=work.timings)
        if len(frame.segments_px) < MIN_REGION_SEGMENTS:
            return not_found
        groups = region_groups(frame, p.matching)
        if paper_only:
            return self._paper_estimate(work, frame, groups, not_found)
        best = self._chosen(work, frame, groups)
        if best is None:
            work.budget.finished()
            not_found.skipped = tuple(work.budget.skipped)
            return not_found
        if regions is not None:
            best = self._likelier_in_places(work, best, image, camera, regions, frame)
        best = self._larger_checked(work, best, frame)
        margin, tied = None, False
        if p.pose.twin_check:
            best, margin, tied = check_twins(best, self.graph, self._refiner, frame, p.pose, work.pool)
            work.lap("symmetry")
        estimate = self._described(work, best, frame, margin, tied)
        work.lap("verification")
        work.timings["total"] = sum(work.timings.values())
        work.budget.finished()
        estimate.skipped = tuple(work.budget.skipped)
        if is_found(estimate, p.pose):
            estimate.found, estimate.R, estimate.t, estimate.covariance = True, best.R, best.t, best.covariance
        return estimate

    def _image_work(self, params: EstimatorParams | None = None, pool: WorkerPool | None = None,
                    timings: dict | None = None) -> ImageWork:
        """One image's view of the estimator, taken at once whatever a parameter change does
        meanwhile (``params`` and ``pool`` in its stead where given: benches); the pools such
        changes retired are closed, as the image before, which used them, has finished (one
        estimator runs one image at a time)."""
        with self._lock:
            p = params or self._params
            work = ImageWork(p, self._hypotheses, self._search, pool or self._pool, self._calibration,
                             TimeBudget.starting_now(p.search.time_budget_ms, self._step_costs),
                             {} if timings is None else timings)
            retired, self._retired = self._retired, []
        for old in retired:
            old.close()
        return work

    def _chosen(self, work: ImageWork, frame: Frame, groups: list) -> Candidate | None:
        """The frame's pose before the larger and twin checks (steps 3-4): the best finalist of
        the generators' candidates or a rival at its place, a small pose only where likelier
        than the search's sizes' best; None without a candidate."""
        climbs: dict = {}  # the view climbs made on this frame (``PoseRefiner._climbed``)
        candidates, best = self._candidates(work, frame, groups, climbs)
        work.budget.generators_done()
        if not candidates:
            return None
        return best if best is not None else self._choice(work, frame, candidates, climbs)

    def _choice(self, work: ImageWork, frame: Frame, candidates: list[Candidate], climbs: dict) -> Candidate:
        """The best finalist of refined ``candidates``, or a rival at its place, a small pose only
        where likelier than the search's sizes' best."""
        p = work.p
        finalists = self._refiner.finalists(candidates, frame, p.pose, work.pool, climbs)
        best = check_rivals(in_working_range(finalists, self.graph, p.pose) or finalists, self.graph, frame, p.pose)
        if "small" in p.search.stages:
            best = self._likelier_than_small(work, best, finalists, frame)
        work.lap("refinement")
        return best

    def choose(self, frame: Frame, candidates: list[Candidate], params: EstimatorParams | None = None,
               pool: WorkerPool | None = None) -> Candidate:
        """The pose ``estimate`` would take among refined ``candidates`` (from ``candidates``)
        before the twin check: the choice, then the larger-pose check where it applies (for
        benches that replay the choice on candidates they examined; ``params`` and ``pool``
        as ``_image_work``'s)."""
        work = self._image_work(params, pool)
        return self._larger_checked(work, self._choice(work, frame, candidates, {}), frame)

    def _larger_checked(self, work: ImageWork, best: Candidate, frame: Frame) -> Candidate:
        """``best``, or the larger pose about its place the larger check finds (``larger_pose``)
        where the check applies and the image's time budget allows it."""
        if not (larger_check_applies(best, work.p, work.search) and work.budget.allows(LARGER_CHECK)):
            return best
        best = larger_pose(best, self.graph, frame, work.p, work.search, work.hypotheses, self._refiner, work.pool)
        work.budget.close()
        work.lap("larger")
        return best

    def _likelier_in_places(self, work: ImageWork, best: Candidate, image: np.ndarray, camera: Camera,
                            regions: np.ndarray, frame: Frame) -> Candidate:
        """``best``, or the pose chosen within one of the colour regions' places alone
        (``colour_places``, ``edges.colour_places``) where it scores more on the whole regions'
        ``frame``: on the LM-O photos the whole regions' search seeded no pose near 12 well-visible
        cats, within the cat's own place 7 of them had a candidate near (docs/results/real_lmo.md)."""
        p = work.p
        for place in colour_places(image, self.graph.colour_histogram, regions, p.edges.colour_places):
            if not work.budget.allows("colour place"):
                break
            within = Frame.detect(image, camera, p.edges, work.pool, scored_tolerances(self.graph, p.pose), place)[1]
            work.lap("edges")
            if len(within.segments_px) < MIN_REGION_SEGMENTS:
                continue
            chosen = self._chosen(work, within, region_groups(within, p.matching))
            if chosen is None:
                continue
            score = float(pose_scores(self.graph, chosen.R[None], chosen.t[None], frame, p.pose)[0])
            if score > best.score:
                best = replace(chosen, score=score)
        return best

    def _described(self, work: ImageWork, best: Candidate, frame: Frame, margin: float | None = None,
                   tied: bool = False) -> Estimate:
        """What the estimate reports of a pose (not yet judged found): its score's shares, the
        error ratio, its size, the shading fit where the graph holds the part's surface and the
        frame its grey levels, and the confidence, which weighs them all."""
        p = work.p
        pairs = edge_pairs(self.graph, best.R, best.t, frame, p)
        shading = None
        if self.graph.surface is not None and frame.gray is not None:
            shading = shading_fit(frame.gray, self.graph.surface, best.R, best.t, frame.camera)
        shares, size, length = pose_shares(self.graph, best.R, best.t, frame, p.pose)
        estimate = Estimate(found=False, R=None, t=None, score=best.score, error_ratio=pairs.error_ratio,
                            view_index=self.graph.nearest_view(best.R, best.t), n_image_segments=len(frame.segments_px),
                            n_matched=pairs.n_matched, n_nearest=pairs.n_nearest,
                            image_segments=pairs.image_segments, model_segments=pairs.model_segments,
                            timings=work.timings, matched_view=int(best.hypothesis.view),
                            symmetry_margin=margin, ambiguous=margin is not None and margin < p.pose.twin_margin,
                            twin_tie=tied,
                            shares=shares, size_pixels=size, model_length_pixels=length,
                            distance=centre_distance(self.graph, best), shading_fit=shading)
        estimate.confidence = work.calibration.confidence(estimate, p.pose.prior)
        return estimate

    def _likelier_than_small(self, work: ImageWork, best: Candidate, finalists: list[Candidate],
                             frame: Frame) -> Candidate:
        """``best``, or where it is smaller than the template search's sizes (a pose the
        ``small`` generator may have brought) the best finalist of the search's sizes if that
        is more probably right: the score of a pose a third the size of another is not
        comparable with it (the small pose has few edge pixels to miss; on the bench such
        poses on clutter props outscored the part at 0.56-0.72), while the confidence was
        fitted with the pose's size among its features and ranked the part first there."""
        smallest = work.search.sizes(frame, work.p.search)[0] / np.sqrt(work.p.search.size_step)

        def small(c: Candidate) -> bool:
            return (c.R @ self.graph.model_center + c.t)[2] > 0 and \
                projected_place(self.graph, c.R, c.t, frame)[1] < smallest

        regular = [c for c in finalists if not small(c)]
        if not small(best) or not regular:
            return best
        other = max(regular, key=lambda c: c.score)
        likelier = self._described(work, other, frame).confidence > self._described(work, best, frame).confidence
        return other if likelier else best

    def part_frame(self, image: np.ndarray, camera: Camera) -> Frame:
        """The image's edges as ``estimate`` sees them for this part: within the part's colour
        regions (``edges.colour_regions``) where they apply, else the whole image's (for benches
        that score other poses on what the estimator saw)."""
        with self._lock:
            p, pool = self._params, self._pool
        return Frame.detect(image, camera, p.edges, pool, scored_tolerances(self.graph, p.pose),
                            self._colour_regions(image, p))[1]

    def _colour_regions(self, image: np.ndarray, p: EstimatorParams) -> np.ndarray | None:
        """The mask of the part's colour regions (``colour_regions``), or None: the whole image."""
        if not p.edges.colour_regions:
            return None
        # a region smaller than a square half the smallest pose's diagonal wide holds no part
        return colour_regions(image, self.graph.colour_histogram, p.edges.colour_region_threshold,
                              (p.pose.min_size_pixels / 2) ** 2)

    def candidates(self, frame: Frame, timings: dict | None = None) -> list[Candidate]:
        """The hypotheses of ``search.generators`` on one image's edges, each refined and
        scored: what ``estimate`` hands to the view climb (for benches of the generators);
        the seconds of each stage are added to ``timings`` if given."""
        work = self._image_work(timings=timings)
        return self._candidates(work, frame, region_groups(frame, work.p.matching), {})[0]

    def _candidates(self, work: ImageWork, frame: Frame, groups: list,
                    climbs: dict) -> tuple[list[Candidate], Candidate | None]:
        """Refined, scored hypotheses of the chosen generators (module doc, steps 2-4), and the
        best of them climbed and polished if a generator was skipped for it (else None);
        ``climbs`` keeps the image's view climbs for the later stages and the finalists; a
        generator after the first starts only while the image's time budget allows."""
        p, search, pool = work.p, work.search, work.pool
        candidates: list[Candidate] = []
        coarse = None  # the template search's, once per image for every stage that needs it
        for n, stage in enumerate(p.search.stages):
            candidates = in_working_range(candidates, self.graph, p.pose)
            if n and not work.budget.allows(*p.search.stages[n:]):
                break
            if n and candidates:
                # the climbed, polished pose decides, not the raw candidates: on the bench a
                # right pose's candidate scored 0.75-0.94 and the climb lifted it, while wrong
                # ones stayed below 0.85 (docs/DECISIONS.md); kept as a start for the final climb
                settled = in_working_range([self._refiner.best(candidates, frame, p.pose, pool, climbs)], self.graph,
                                           p.pose)
                work.lap("refinement")
                if settled and settled[0].score >= p.search.enough_score:
                    return settled, settled[0]
                candidates = candidates + settled
            if stage in ("search", "seeded", "windows") and coarse is None:
                coarse = search.coarse(frame, p.search, pool, distances=p.pose.distances)
                work.lap("search")
            if stage == "search":
                # not aligned on edge pixels: the search's many coarse templates, aligned, fit
                # clutter and occluders as well as a 30 % hidden part (docs/results/refinement.md)
                candidates += self._refiner.verify(search.best(coarse, frame, p.search.hypotheses, p.search), frame,
                                                   p.pose, pool)
                work.lap("refinement")
            elif stage == "windows":
                windows = [segments_within(frame, center, p.search.seed_window * size / 2)
                           for center, size in search.places(coarse, p.search.windows)]
                candidates = self._tetrads(work, frame, [windows], candidates)
            elif stage in ("seeded", "small"):
                seeds = search.best(coarse, frame, p.search.seeds, p.search) if stage == "seeded" else \
                    small_part_seeds(frame, groups, p.search, search, p.pose.min_size_pixels, p.pose.distances, pool)
                work.lap("search")
                matched = work.hypotheses.at_seeds(seeds, frame, p.search.seed_window, p.matching, pool)
                work.lap("matching")
                verified = self._refiner.verify(best_covered(matched, p.search.hypotheses), frame, p.pose, pool)
                candidates += self._realigned(work, frame, verified)
                work.lap("refinement")
            else:
                candidates = self._tetrads(work, frame, [groups[:1], groups[1:]], candidates)
        return in_working_range(candidates, self.graph, p.pose), None

    def _tetrads(self, work: ImageWork, frame: Frame, batches: list[list[np.ndarray]],
                 candidates: list[Candidate]) -> list[Candidate]:
        """``candidates`` with the tetrad generator's on batches of regions (segment indices),
        batch by batch until a pose is clear: for the whole image, then its clusters, a clear
        pose in the whole image means the clusters (pieces of the same part, or the part
        among clutter) cannot add one, and their pre-filter, matching and verification are saved.
        The hypotheses are aligned on edge pixels (``_realigned``) only after every batch was
        verified on the lines: among clutter the whole image's hypotheses score low while a
        cluster's hold the part (the demo's images: 0.06-0.47 against 0.83-0.97), and aligning
        the first batch would be wasted."""
        p, pool = work.p, work.pool
        first = len(candidates)
        for batch in batches:
            if not batch or any(c.score >= CLEAR_SCORE for c in in_working_range(candidates, self.graph, p.pose)):
                break
            jobs = work.hypotheses.shortlist_groups(frame, batch, p.matching, pool)
            work.lap("prefilter")
            matched = work.hypotheses.match(jobs, p.matching, pool)
            work.lap("matching")
            candidates = candidates + self._refiner.verify(best_per_region(matched, p.matching.hypotheses), frame,
                                                           p.pose, pool)
            work.lap("refinement")
        candidates = candidates[:first] + self._realigned(work, frame, candidates[first:])
        work.lap("refinement")
        return candidates

    def _realigned(self, work: ImageWork, frame: Frame, verified: list[Candidate]) -> list[Candidate]:
        """One stage's verified hypotheses, also aligned on edge pixels (``PoseRefiner.realign``)
        unless one already scores ``search.enough_score`` on the lines: the starts the
        alignment rescues come from stages whose line ends all score low, and on the tuning
        images no stage above it owed a success to it (docs/results/refinement.md)."""
        if not verified or max(c.score for c in verified) >= work.p.search.enough_score:
            return verified
        return self._refiner.realign(verified, frame, work.p.pose, work.pool)

    def _paper_estimate(self, work: ImageWork, frame: Frame, groups: list, not_found: Estimate) -> Estimate:
        """The best-covered hypothesis of all regions at once, its view as the pose."""
        g, p = self.graph, work.p
        regions = [r for r in (normalised_region(indices, frame, p.matching) for indices in groups) if r is not None]
        jobs = work.hypotheses.shortlist(regions, p.matching, work.pool)
        work.lap("prefilter")
        matched = work.hypotheses.match(jobs, p.matching, work.pool)
        work.lap("matching")
        work.timings["total"] = sum(work.timings.values())
        if not matched:
            return not_found
        best = max(matched, key=lambda h: h.coverage)
        R, t = pose_from_similarity(g.view_rotations[best.view], g.model_center, scale=best.scale, phi=best.phi,
                                    shift=best.shift, R_align=best.region.R_align)
        pairs = edge_pairs(g, R, t, frame, p)
        return Estimate(found=True, R=R, t=t, score=best.coverage, error_ratio=pairs.error_ratio,
                        view_index=g.nearest_view(R, t), n_image_segments=not_found.n_image_segments,
                        n_matched=pairs.n_matched, n_nearest=pairs.n_nearest, image_segments=pairs.image_segments,
                        model_segments=pairs.model_segments, timings=work.timings, matched_view=best.view)

def is_found(estimate: Estimate, p: PoseParams) -> bool:
    """The found rule: the confidence decides (docs/results/confidence.md), above a floor on
    the score that keeps a pose the verification barely confirms from being reported; a pose
    outside the working range (``pose.min_distance`` - ``max_distance``) cannot be right."""
    return (estimate.score >= p.min_score and estimate.confidence >= p.min_confidence
            and p.within_distance(estimate.distance)
            and (p.min_shading_fit == 0 or (estimate.shading_fit or 0.0) >= p.min_shading_fit))


def not_found_reason(estimate: Estimate, p: PoseParams) -> str:
    """Why ``is_found`` refused ``estimate``, in words for logs and diagnostics: the working
    range if the pose lies outside it, else the score and the confidence with their floors."""
    if estimate.score > 0 and not p.within_distance(estimate.distance):
        return (f"the best pose lies {estimate.distance:.3g} m away, outside pose.min_distance {p.min_distance:g} - "
                f"pose.max_distance {p.max_distance:g}")
    shading = (f"; shading fit {estimate.shading_fit:.2f}, pose.min_shading_fit {p.min_shading_fit:g}"
               if estimate.shading_fit is not None else "")
    return (f"score {estimate.score:.2f}, pose.min_score {p.min_score:g}; confidence {estimate.confidence:.2f}, "
            f"pose.min_confidence {p.min_confidence:g}{shading}")


def in_working_range(candidates: list[Candidate], graph: AspectGraph, p: PoseParams) -> list[Candidate]:
    """The candidates whose model centre lies in the working range: the others cannot be
    right, and a rescaled fit to a piece of the part at another depth can outscore the
    truth (docs/results/symmetry.md)."""
    if p.distances == (0.0, 0.0):
        return candidates
    return [c for c in candidates if p.within_distance(centre_distance(graph, c))]


def template_search(graph: AspectGraph, p: SearchParams) -> TemplateSearch | None:
    """The template search if the parameters use it, else None: a node of the tetrad
    generator alone then starts without deriving templates and warming the search's kernel."""
    return None if p.stages == ("tetrad",) else TemplateSearch(graph, p)


"""The tetrad hypothesis generator: which views of the aspect graph, turned, scaled and
shifted how, explain each candidate region (seed paper section 6, ``matching``).

For every region the pre-filter shortlists (view, rotation) jobs (``prefilter``); the
jobs of a region run as one batch through the correspondence step (``matching.align``);
each aligned job becomes a ``Hypothesis``: the similarity from the view's orthographic
coordinates (metres) to the region's virtual image (normalised coordinates), which
``refinement.pose_from_similarity`` turns into a first metric pose.

The worker threads (``workers.WorkerPool``, ``matching.workers``) share the pre-filter's
views and split each region's batch of jobs between them; results do not depend on how
the work is split.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from ..aspect_graph import AspectGraph
from ..camera import to_virtual
from ..metric_space import outline_normalisation
from ..params import MatchParams
from . import matching
from .frame import Frame
from .prefilter import ChamferPrefilter, orientation_histogram, orientation_spectra, rotation_candidates
from .regions import MIN_REGION_SEGMENTS, Region, normalised_region, segments_within
from .workers import SERIAL, WorkerPool


@dataclass
class Hypothesis:
    """A view matched to a region: the similarity view (metres) -> virtual image (normalised)."""

    region: Region
    view: int
    scale: float
    phi: float
    shift: np.ndarray
    coverage: float  # F-measure of the two-way edge coverage after alignment


class ViewLibrary:
    """Per-view features for matching, computed once from the aspect graph."""

    def __init__(self, graph: AspectGraph, max_segments: int):
        self.normalisation = []
        self.features: list[matching.SegmentFeatures] = []
        for v in range(graph.n_views):
            metric = graph.view_xy(v)
            metric = metric[matching.longest(metric, max_segments)]
            norm = outline_normalisation(metric)
            self.normalisation.append(norm)
            self.features.append(matching.describe(norm.apply(metric)))
        histograms = np.stack([orientation_histogram(f.orientations, f.lengths) for f in self.features])
        self.orientation_spectra = orientation_spectra(histograms)
        #: every view's segments in one array, view v at ``offsets[v]:offsets[v + 1]``: the
        #: compiled matching (``matching.align``) takes a batch's views from it by index
        self.segments = np.ascontiguousarray(np.concatenate([f.segments for f in self.features]))
        self.offsets = np.concatenate([[0], np.cumsum([len(f.segments) for f in self.features])]).astype(np.int64)
        self.prefilter = ChamferPrefilter([f.segments for f in self.features])

    def shortlist(self, region: Region, p: MatchParams, pool: WorkerPool) -> list[tuple[int, float]]:
        """The (view, rotation) pairs closest to the region by oriented chamfer distance."""
        phis = rotation_candidates(self.orientation_spectra, region.orientation_histogram, p.rotation_candidates,
                                   pool)
        views, which = self.prefilter.shortlist(region.distance_maps, phis, p.shortlist_size, pool)
        return [(int(v), float(phis[v, r])) for v, r in zip(views, which)]


#: one matching job: a region, a view and the in-plane rotation to try it at
Job = tuple[Region, int, float]


class TetradHypotheses:
    """Hypotheses for regions by the pre-filter and the bipartite matching of tetrads.

    Built for one ``max_model_segments`` (the view features); every other parameter, and
    the worker threads, come with each call, so an image keeps what it started with."""

    def __init__(self, graph: AspectGraph, p: MatchParams):
        self.graph = graph
        self._views = ViewLibrary(graph, p.max_model_segments)

    def shortlist(self, regions: list[Region], p: MatchParams, pool: WorkerPool) -> list[Job]:
        """The pre-filter's (view, rotation) jobs of every region, region by region."""
        return [(region, view, phi) for region in regions for view, phi in self._views.shortlist(region, p, pool)]

    def shortlist_groups(self, frame: Frame, groups: list[np.ndarray], p: MatchParams,
                         pool: WorkerPool) -> list[Job]:
        """``shortlist`` of groups of image segments (indices) normalised as regions
        (``normalised_region``; a group that cannot be is skipped). With at least as many
        groups as threads, each group is one task on the threads, normalised and shortlisted
        there: the normalisation's numpy steps of one group then run beside another's
        pre-filter kernels, where group by group they ran alone. Fewer groups (the whole
        image) split each one's views between the threads instead; the same jobs either way."""
        def jobs_of(indices: np.ndarray, views_pool: WorkerPool) -> list[Job]:
            region = normalised_region(indices, frame, p)
            return [] if region is None else self.shortlist([region], p, views_pool)

        if pool.size > 1 and len(groups) >= pool.size:
            per_group = pool.map(lambda indices: jobs_of(indices, SERIAL), groups)
        else:
            per_group = [jobs_of(indices, pool) for indices in groups]
        return [job for jobs in per_group for job in jobs]

    def match(self, jobs: list[Job], p: MatchParams, pool: WorkerPool) -> list[Hypothesis]:
        """Hypotheses of the jobs, in job order. Consecutive jobs of one region run together
        (``_match_batch``), split into one batch per worker thread."""
        batches = []
        for _, run in itertools.groupby(jobs, key=lambda job: id(job[0])):
            run = list(run)
            batches += [run[chunk] for chunk in pool.split(len(run))]
        return [h for batch in pool.map(lambda batch: self._match_batch(batch, p), batches) for h in batch]

    def at_seeds(self, seeds: list[Hypothesis], frame: Frame, window: float, p: MatchParams,
                 pool: WorkerPool) -> list[Hypothesis]:
        """Item 2 of issue 11: each seed (a view placed at a centre, size and in-plane angle,
        e.g. a template of ``search``) matched by Kuhn-Munkres to the image segments around
        it, normalised with the seed's own frame rather than their hull; so an occluder or a
        neighbour in the window moves no normalisation, and the nearest group's similarity
        corrects the seed. Returns the aligned hypotheses (coverage ranked like the regions').

        The window is the image segments whose midpoints lie within ``window`` times the
        seed's part radius of its centre; a seed with fewer than ``MIN_REGION_SEGMENTS``
        there gives nothing."""
        jobs = [job for job in (self._seed_job(seed, frame, window, p) for seed in seeds) if job is not None]
        return self.match(jobs, p, pool)

    def _seed_job(self, seed: Hypothesis, frame: Frame, window: float, p: MatchParams) -> Job | None:
        """The seed's window as a region normalised so that the seed's view, normalised as
        the views are (``ViewLibrary``) and turned by the seed's angle, lands on it."""
        camera, R_align = frame.camera, seed.region.R_align
        ray = R_align @ np.array([seed.shift[0], seed.shift[1], 1.0])  # through the model centre
        center_px = camera.project(ray)
        radius_px = window * seed.scale * self.graph.model_diameter * camera.focal / 2
        inside = segments_within(frame, center_px, radius_px)
        if len(inside) < MIN_REGION_SEGMENTS:
            return None
        inside = inside[matching.longest(frame.segments_n[inside], p.max_image_segments)]
        norm = self._views.normalisation[seed.view]
        turn = matching.rotations(np.array([seed.phi]))[0]
        # view metres -> virtual image: scale R(phi) x + shift; the view's normalisation
        # centre and scale carried through it give the region's
        center = seed.shift + seed.scale * turn @ norm.center
        scale = seed.scale * norm.scale
        virtual = to_virtual(frame.segments_n[inside], R_align)
        region = Region(R_align=R_align, center=center, scale=scale,
                        features=matching.describe((virtual - center) / scale), orientation_histogram=None,
                        distance_maps=None)
        return region, seed.view, seed.phi

    def _match_batch(self, jobs: list[Job], p: MatchParams) -> list[Hypothesis]:
        """``matching.align`` for jobs of one region at once (one compiled call, the GIL
        released), each aligned job composed into the similarity view metres -> virtual image."""
        region = jobs[0][0]
        views = np.array([view for _, view, _ in jobs], np.int64)
        phi = np.array([phi for _, _, phi in jobs])
        aligned = matching.align(self._views.segments, self._views.offsets, views, phi, region.features, p)
        if len(aligned.jobs) == 0:
            return []
        views = views[aligned.jobs]
        # compose: view metres -> view normalised -> region normalised -> virtual image
        norm_v = [self._views.normalisation[v] for v in views]
        scale = region.scale * aligned.scale / np.array([n.scale for n in norm_v])
        turned = np.einsum("jkl,jl->jk", matching.rotations(aligned.angle), np.array([n.center for n in norm_v]))
        shift = region.center + region.scale * aligned.shift - scale[:, None] * turned
        return [Hypothesis(region, int(views[j]), float(scale[j]), float(aligned.angle[j]), shift[j],
                           float(aligned.coverage[j])) for j in range(len(views))]


def best_covered(hypotheses: list[Hypothesis], count: int) -> list[Hypothesis]:
    """The ``count`` hypotheses of widest two-way edge coverage, best first."""
    return sorted(hypotheses, key=lambda h: -h.coverage)[:count]


def best_per_region(hypotheses: list[Hypothesis], count: int) -> list[Hypothesis]:
    """The ``count`` best-covered hypotheses of every region: a small region (the part
    among clutter) must not lose its candidates to the whole image's."""
    chosen = []
    for region_id in dict.fromkeys(id(h.region) for h in hypotheses):  # regions in order, not by address
        own = [h for h in hypotheses if id(h.region) == region_id]
        chosen += best_covered(own, count)
    return chosen

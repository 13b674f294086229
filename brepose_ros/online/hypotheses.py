"""The tetrad hypothesis generator: which views of the aspect graph, turned, scaled and
shifted how, explain each candidate region (seed paper section 6, ``matching``).

For every region the pre-filter shortlists (view, rotation) jobs (``prefilter``); the
jobs, of one region or many, run in batches through the correspondence step
(``matching.align``); each aligned job becomes a ``Hypothesis``: the similarity from the view's orthographic
coordinates (metres) to the region's virtual image (normalised coordinates), which
``refinement.pose_from_similarity`` turns into a first metric pose.

The worker threads (``workers.WorkerPool``, ``matching.workers``) share the pre-filter's
views and split the jobs between them; results do not depend on how the work is split.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..aspect_graph import AspectGraph
from ..camera import to_virtual
from ..metric_space import outline_normalisation
from ..params import MatchParams
from . import matching
from .frame import Frame
from .prefilter import ChamferPrefilter, orientation_histogram, orientation_spectra, rotation_candidates
from .regions import MIN_REGION_SEGMENTS, Region, normalised_region, segment_windows
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
        #: the normalisations' centres (V, 2) and scales (V,) as arrays, for batches of jobs
        self.centers = np.array([n.center for n in self.normalisation])
        self.scales = np.array([n.scale for n in self.normalisation])
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
        """Hypotheses of the jobs, in job order: the jobs dealt into one chunk per worker
        thread (each thread a share of every region's, whose jobs cost alike), each chunk one
        compiled call (``matching.align``, the GIL released) whatever regions its jobs are of,
        each aligned job composed into the similarity view metres -> virtual image. A region's
        jobs best come together (its geometry is then found once per run of them)."""
        if not jobs:
            return []
        regions = list({id(region): region for region, _, _ in jobs}.values())  # in order of their first job
        number = {id(region): k for k, region in enumerate(regions)}
        of_region = np.array([number[id(region)] for region, _, _ in jobs], np.int64)
        views = np.array([view for _, view, _ in jobs], np.int64)
        phi = np.array([phi for _, _, phi in jobs], float)
        segments = [region.features.segments for region in regions]
        region_segments = np.ascontiguousarray(np.concatenate(segments))
        region_offsets = np.concatenate([[0], np.cumsum([len(s) for s in segments])]).astype(np.int64)
        centers = np.array([region.center for region in regions])
        scales = np.array([region.scale for region in regions])
        library = self._views

        def chunk(rows: slice) -> tuple[np.ndarray, list[Hypothesis]]:
            aligned = matching.align(library.segments, library.offsets, views[rows], phi[rows], region_segments,
                                     region_offsets, of_region[rows], p)
            view, region = views[rows][aligned.jobs], of_region[rows][aligned.jobs]
            # compose: view metres -> view normalised -> region normalised -> virtual image
            scale = scales[region] * aligned.scale / library.scales[view]
            turned = np.einsum("jkl,jl->jk", matching.rotations(aligned.angle), library.centers[view])
            shift = centers[region] + scales[region][:, None] * aligned.shift - scale[:, None] * turned
            return np.arange(len(jobs))[rows][aligned.jobs], [
                Hypothesis(regions[r], int(v), float(sc), float(a), sh, float(c))
                for r, v, sc, a, sh, c in zip(region, view, scale, aligned.angle, shift, aligned.coverage)]

        chunks = pool.map(chunk, pool.deal(len(jobs)))
        hypotheses = [h for _, hypotheses in chunks for h in hypotheses]
        return [hypotheses[k] for k in np.argsort(np.concatenate([index for index, _ in chunks]))]

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
        return self.match(self._seed_jobs(seeds, frame, window, p), p, pool)

    def _seed_jobs(self, seeds: list[Hypothesis], frame: Frame, window: float, p: MatchParams) -> list[Job]:
        """Each seed's window as a region normalised so that the seed's view, normalised as
        the views are (``ViewLibrary``) and turned by the seed's angle, lands on it. The
        windows, centres and scales of all seeds are found at once, as arrays: one seed at a
        time, their small numpy steps cost ~50 us a seed, 128 seeds an image."""
        if not seeds:
            return []
        camera = frame.camera
        R_align = np.stack([seed.region.R_align for seed in seeds])
        shift = np.array([seed.shift for seed in seeds])
        scale = np.array([seed.scale for seed in seeds])
        view = np.array([seed.view for seed in seeds], np.int64)
        # the rays through the model centres (a stacked matmul is each seed's own product, to the bit)
        rays = R_align @ np.concatenate([shift, np.ones((len(seeds), 1))], axis=1)[:, :, None]
        radius_px = window * scale * self.graph.model_diameter * camera.focal / 2
        inside = segment_windows(frame, camera.project(rays[:, :, 0]), radius_px)
        # each window's longest segments: all segments ranked once, each window taking its first
        ranked = matching.longest(frame.segments_n, len(frame.segments_n))
        taken = inside[:, ranked] & (np.cumsum(inside[:, ranked], axis=1) <= p.max_image_segments)
        # view metres -> virtual image: scale R(phi) x + shift; the view's normalisation
        # centre and scale carried through it give the region's
        turn = scale[:, None, None] * matching.rotations(np.array([seed.phi for seed in seeds]))
        center = shift + (turn @ self._views.centers[view][:, :, None])[:, :, 0]
        region_scale = scale * self._views.scales[view]
        jobs = []
        for k in np.nonzero(inside.sum(axis=1) >= MIN_REGION_SEGMENTS)[0]:
            seed = seeds[k]
            virtual = to_virtual(frame.segments_n[ranked[taken[k]]], seed.region.R_align)
            region = Region(R_align=seed.region.R_align, center=center[k], scale=float(region_scale[k]),
                            features=matching.describe((virtual - center[k]) / region_scale[k]),
                            orientation_histogram=None, distance_maps=None)
            jobs.append((region, seed.view, seed.phi))
        return jobs


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

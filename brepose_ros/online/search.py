"""The template search: a hypothesis generator that never normalises an image region.

Where the tetrad generator (``hypotheses``) normalises a whole region of image segments,
so that an occluder or a neighbour in the region moves its centre and scale, this one
slides explicit templates over the image, as LINE-2D (Hinterstoisser et al., PAMI 2012)
and the shape-based matching of Ulrich, Wiedemann and Steger do: a template is a view of
the aspect graph turned by an in-plane angle and scaled to a pixel size, drawn as
``SearchParams.template_points`` points with the direction of the model edge they lie on;
it scores at an image position by the share of its points that find an image edge pixel
of like direction (modulo 180 degrees: a metal edge flips polarity with the light) near
them. Occlusion only removes points from that share, and clutter adds edges only where
it lies.

Steps, per image:

1. Response maps (``ResponseMaps``): for each of ``EdgeEvidence.BINS`` direction bins the
   Canny pixels of that bin or the two next to it, pooled onto a grid ``coarse_factor``
   times coarser and spread by ``spread`` cells: a template point hits when its cell is set.
2. Chance (a-contrario): a template that lands on dense edges hits by chance. The expected
   hits of a template at a position are its points' count per bin times the density of
   that bin's map in a window the size of the template; the score is the share of hits
   above that chance, ``(hits - E) / K``. Views whose points nearly all share one direction
   (seen edge-on: they fit any pair of straight edges) are not searched at all
   (``MAX_ONE_DIRECTION_SHARE``); the local chance alone did not hold them down.
3. Coarse search (``score_templates``, a numba kernel that releases the GIL): every coarse
   view (``TemplateLibrary.coarse_views``, the graph views nearest a sparser golden
   spiral) x in-plane angle x size, at every coarse cell; each template keeps its best
   position. A chunk of templates is one call, so threads share the templates
   (``workers.WorkerPool``), and the chunks' output is ranked again as one call's
   (``rank_as_one_call``): the same templates whatever the number of threads. A first pass
   counts a quarter of the points (``PROBE_STRIDE``) on blocks of 4 x 4 cells (``BLOCK``),
   then cell by cell between the first and the last block of a row where they hit often
   enough (``probe_share``); the rest of the points only at cells where those do (along
   the row from the first to the last of them at once where many do), or else a quarter
   at a time, and no further once the cell cannot beat the template's best or the
   ``ranked_templates``-th best template so far (the seeds and hypotheses lie among the
   ranked; the windows' distinct places can reach past them: on the clean latency image 3,
   split between two threads before ``rank_as_one_call``, to templates one call gave up).
4. The best distinct templates become ``Hypothesis`` objects on the virtual camera through
   their centre (``camera.virtual_alignment``): the refinement (``refinement``) turns them
   into metric poses, pulls them onto the image lines, climbs over the graph's views and
   scores them like the tetrad generator's. Duplicates (same view, about one angle step
   and one position) are dropped; other views at one position are kept. Or (the
   estimator's ``seeded`` and ``windows`` generators) they seed the bipartite matching
   (``TetradHypotheses.at_seeds``), or their best places (``places``) become regions.

The template points are derived from the graph's view edges when the estimator starts
(0.06 s of CPU for 1,505 views), not stored in the graph file (docs/DECISIONS.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

from ..aspect_graph import AspectGraph
from ..camera import virtual_alignment
from ..params import SearchParams, field_ranges
from ..viewsphere import fibonacci_directions
from .frame import Frame
from .hypotheses import Hypothesis
from .regions import Region
from .scoring import EdgeEvidence
from .workers import SERIAL, WorkerPool

BINS = EdgeEvidence.BINS
#: the kernel's first pass counts every PROBE_STRIDE-th point of a template (a quarter)
PROBE_STRIDE = 4
#: a view whose template points run in one direction (within three bins, 67 degrees) for
#: more than this share is seen nearly edge-on: it fits any pair of straight image edges,
#: so the search does not start from it (the refinement's view climb still reaches it)
MAX_ONE_DIRECTION_SHARE = 0.8
#: the kernel counts all points along a span of cells once more than 1 in this many cells of
#: the span pass the probes (textured images): 1.5-2.8x faster there than cell by cell
DENSE_ROW_SHARE = 8
#: a position passes the probes only if their hits beat the response maps' density (the share
#: of points that hit anywhere by chance) by this much, when that asks more than
#: ``min_coarse_share``: on the LM-O photos the maps are half set and every position passed
CHANCE_MARGIN = 0.25
#: the kernel adds a row of cells LANES at a time, a whole number of vector adds (the cells
#: past a span's end are counted too, never read): 0.91x its CPU on the occluded latency
#: images against adds that end at the span's end, whose scalar remainder outweighed short spans
LANES = 8
#: the kernel's first pass counts the probes on blocks of BLOCK x BLOCK cells: 4 rather than 2
#: (a quarter of the adds, a little wider spans of cells after it) took 0.88x the kernel's
#: CPU on the occluded latency images at ``min_coarse_share`` 0.5, the same scores and cells
BLOCK = 4


class TemplateLibrary:
    """Per graph view, ``template_points`` points along its visible edges (metres, view
    coordinates centred on the model centre) with the direction of their edge (radians,
    modulo pi); and the coarse views the search starts from."""

    def __init__(self, graph: AspectGraph, p: SearchParams):
        self.graph = graph
        self.n_points = p.template_points
        self.points = np.zeros((graph.n_views, p.template_points, 2), np.float32)
        self.angles = np.zeros((graph.n_views, p.template_points), np.float32)
        for v in range(graph.n_views):
            self.points[v], self.angles[v] = template_points(graph.view_xy(v), p.template_points)
        directions = fibonacci_directions(p.coarse_view_step_deg)
        coarse = np.unique(np.argmax(directions @ graph.view_directions.T, axis=1))
        self.coarse_views = coarse[[one_direction_share(self.angles[v]) <= MAX_ONE_DIRECTION_SHARE for v in coarse]]
        #: the radius (metres) of each view's template about the model centre: sizes are
        #: the part's diameter in pixels, so a view seen edge-on is as far as the others
        self.diameter = graph.model_diameter
        #: the narrowest coarse view's widest span (its points' farthest pair) as a share of
        #: the diameter: a part whose outline fits in a region of that span is at most
        #: span / share across (``TemplateSearch.sizes``)
        self.narrowest_span_share = min((widest_span(self.points[v]) for v in self.coarse_views),
                                        default=self.diameter) / self.diameter
        #: the farthest template point from the model centre as a share of the diameter: at most
        #: 0.5 with a graph's own diameter (its bounding box's diagonal), more in a hand-made graph
        self.reach_share = float(np.hypot(self.points[..., 0], self.points[..., 1]).max(initial=0.0)) / self.diameter


def widest_span(points: np.ndarray) -> float:
    """The largest distance between two of the points (K, 2)."""
    return float(np.sqrt(((points[:, None, :] - points[None, :, :]) ** 2).sum(axis=-1).max()))


def template_points(segments: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points evenly spaced by length along segments (N, 2, 2) and the direction
    of the segment each lies on (modulo pi). A view without segments gives points at 0."""
    delta = segments[:, 1] - segments[:, 0]
    lengths = np.hypot(delta[:, 0], delta[:, 1])
    total = lengths.sum()
    if len(segments) == 0 or total <= 0:
        return np.zeros((count, 2)), np.zeros(count)
    # every probe-th point first: the search's first pass counts a spread-out subset
    along = (np.argsort(np.arange(count) % PROBE_STRIDE, kind="stable") + 0.5) / count * total
    ends = np.cumsum(lengths)
    which = np.minimum(np.searchsorted(ends, along), len(segments) - 1)
    frac = (along - (ends[which] - lengths[which])) / np.maximum(lengths[which], 1e-12)
    points = segments[which, 0] + frac[:, None] * delta[which]
    return points, np.mod(np.arctan2(delta[which, 1], delta[which, 0]), np.pi)


def one_direction_share(angles: np.ndarray) -> float:
    """The largest share of directions (modulo pi) within three neighbouring bins."""
    counts = np.bincount((np.mod(angles, np.pi) / np.pi * BINS).astype(int) % BINS, minlength=BINS)
    return float(max(counts[b] + counts[(b + 1) % BINS] + counts[b - 1] for b in range(BINS)) / max(len(angles), 1))


@dataclass
class ResponseMaps:
    """One image's coarse response maps (step 1 of the module doc) and their chance."""

    maps: np.ndarray  # (BINS, H + 2 pad, W + 2 pad) uint8 0/1, padded with 0
    pad: int
    factor: int
    shape: tuple[int, int]  # coarse (H, W)
    #: (BLOCK, BLOCK, BINS, HB, WB): ``bounds[py, px, b, Y, X]`` is set if ``maps[b]`` is set in
    #: any of the BLOCK x BLOCK cells from (BLOCK Y + py, BLOCK X + px): the kernel's block pass
    #: reads rows of it
    bounds: np.ndarray
    #: the image cell (y, x) of the maps' first unpadded cell, and the whole image's coarse
    #: (H, W): maps of a box cover only the cells whose templates can reach its edges
    origin: tuple[int, int]
    image_shape: tuple[int, int]

    @classmethod
    def of(cls, evidence: EdgeEvidence, factor: int, spread: int, pad: int,
           box: tuple[int, int, int, int] | None = None, pool: WorkerPool = SERIAL) -> "ResponseMaps":
        """The maps of the edge pixels, only those within ``box`` (x0, y0, x1, y1 pixels) if
        given, and then only over the cells within ``spread + pad`` of the box: a template at a
        cell farther off reaches no set cell, and a patch's box is a fraction of the image; one
        job per bin on the ``pool``'s threads
        (OpenCV's dilations, which release the GIL), each with its bin's ``bounds`` (1-2 ms of
        numpy in the calling thread for all bins at once)."""
        h, w = evidence.shape
        hc, wc = -(-h // factor), -(-w // factor)
        top, left, bottom, right = 0, 0, hc, wc
        if box is not None:
            x0, y0, x1, y1 = box
            grow = spread + pad
            top, left = max(y0 // factor - grow, 0), max(x0 // factor - grow, 0)
            bottom, right = min(-(-y1 // factor) + grow, hc), min(-(-x1 // factor) + grow, wc)
        block = np.ones((factor, factor), np.uint8)
        kernel = np.ones((2 * spread + 1, 2 * spread + 1), np.uint8)
        maps = np.zeros((BINS, bottom - top + 2 * pad, right - left + 2 * pad), np.uint8)

        def of_bin(b: int) -> np.ndarray:
            like = evidence.like_edges[b, top * factor:bottom * factor, left * factor:right * factor]
            if box is not None:
                x0, y0, x1, y1 = np.subtract(box, [left * factor, top * factor] * 2)
                inside = np.zeros_like(like)
                inside[y0:y1, x0:x1] = like[y0:y1, x0:x1]
                like = inside
            # the maximum over each factor x factor block of pixels: a dilation anchored at the
            # block's first pixel, sampled there (a numpy reduction over the blocks took 30x longer)
            pooled = cv2.dilate(like, block, anchor=(0, 0))[::factor, ::factor]
            maps[b, pad:pad + bottom - top, pad:pad + right - left] = cv2.dilate(pooled, kernel)
            return block_bounds(maps[b:b + 1])

        bounds = np.concatenate(pool.map(of_bin, range(BINS)), axis=2)
        return cls(maps, pad, factor, (bottom - top, right - left), bounds, (top, left), (hc, wc))

    def chance(self, window: int) -> np.ndarray:
        """(BINS, H, W) float32: each bin's share of set cells in a ``window``-wide square
        about each cell (outside the image counts as unset, as in the search)."""
        return self.chances([window])[0]

    def chances(self, windows: list[int], pool: WorkerPool = SERIAL) -> np.ndarray:
        """(S, BINS, H, W): ``chance`` of each window, one job per bin on the ``pool``'s threads
        (OpenCV's box filters, which release the GIL), each writing its bin in place (stacking
        the bins' maps afterwards was a 4 MB copy in the calling thread)."""
        hc, wc = self.shape
        out = np.empty((len(windows), BINS, hc, wc), np.float32)

        def of_bin(b: int) -> None:
            # the image's cells alone: the padding is unset, as the constant border is (a fifth of the
            # padded map's area at the largest sizes; the window sums of 0 and 1 are exact either way)
            cells = self.maps[b, self.pad:self.pad + hc, self.pad:self.pad + wc].astype(np.float32)
            for s, window in enumerate(windows):
                cv2.boxFilter(cells, -1, (window, window), dst=out[s, b], normalize=True,
                              borderType=cv2.BORDER_CONSTANT)

        pool.map(of_bin, range(BINS))
        return out


def block_bounds(maps: np.ndarray) -> np.ndarray:
    """``ResponseMaps.bounds`` of maps (BINS, H, W): the maximum over BLOCK x BLOCK cells,
    split by the remainders of its first row and column divided by BLOCK so that the kernel
    reads each as a plain row."""
    bins, h, w = maps.shape
    padded = np.zeros((bins, h + BLOCK, w + BLOCK), np.uint8)
    padded[:, :h, :w] = maps
    rows = padded[:, :h + 1]  # the maximum over BLOCK rows, then over BLOCK columns of that
    for dy in range(1, BLOCK):
        rows = np.maximum(rows, padded[:, dy:dy + h + 1])
    block = rows[:, :, :w + 1]
    for dx in range(1, BLOCK):
        block = np.maximum(block, rows[:, :, dx:dx + w + 1])
    out = np.zeros((BLOCK, BLOCK, bins, (h + 2 * BLOCK - 1) // BLOCK, (w + 2 * BLOCK - 1) // BLOCK), np.uint8)
    for py in range(BLOCK):
        for px in range(BLOCK):
            part = block[:, py::BLOCK, px::BLOCK]
            out[py, px, :, :part.shape[1], :part.shape[2]] = part
    return out


@njit(nogil=True, cache=True)
def _keep_largest(heap, size, value):
    """Push ``value`` into the min-heap ``heap[:size]`` of the largest ``len(heap)`` values
    pushed so far; returns the new size (``heap[0]`` is the smallest kept once full)."""
    if size < len(heap):
        i, size = size, size + 1
        heap[i] = value
        while i > 0 and heap[(i - 1) // 2] > heap[i]:
            parent = (i - 1) // 2
            heap[parent], heap[i] = heap[i], heap[parent]
            i = parent
        return size
    if value <= heap[0]:
        return size
    heap[0], i = value, 0
    while 2 * i + 1 < size:
        child = 2 * i + 1
        if child + 1 < size and heap[child + 1] < heap[child]:
            child += 1
        if heap[i] <= heap[child]:
            break
        heap[i], heap[child] = heap[child], heap[i]
        i = child
    return size


@njit(nogil=True, cache=True)
def score_templates(maps, bounds, pad, dx, dy, bins, size_index, chance, probes, min_share, keep, best_score,
                    best_y, best_x):
    """Coarse search kernel over templates ``t`` (rows of dx, dy, bins: (T, K) offsets in
    coarse cells and direction bins of each template's points; ``size_index`` (T,) picks the
    chance maps (S, BINS, H, W) of its size). Writes each template's best score, the share
    of its points that hit minus the share expected by chance (module doc), and where.

    Three passes: the first ``probes`` points (spread along the template) are counted on
    BLOCK x BLOCK blocks of cells (``ResponseMaps.bounds``: a point hits a block if it hits any of
    its cells); cell by cell from the first to the last block of a row where at least
    ``min_share`` of them hit; only cells where at least ``min_share`` of them hit are
    counted in full (along the row from the first to the last of them where many do,
    ``DENSE_ROW_SHARE``).

    Only the ``keep`` best templates are ranked (``keep`` 0: all): a template that cannot
    beat the ``keep``-th best so far gets score -1, so its cells are given up early. The
    ``keep`` best of all templates get the same scores and cells as without the limit.

    ``maps`` and ``bounds`` must be C-contiguous: a point's rows are read as slices of them, flat."""
    n_templates, k = dx.shape
    h, w = chance.shape[2], chance.shape[3]
    hb, wb = (h + BLOCK - 1) // BLOCK, (w + BLOCK - 1) // BLOCK
    blocks = bounds.reshape(-1)
    block_row, block_plane = bounds.shape[4], bounds.shape[3] * bounds.shape[4]
    block_acc = np.zeros((hb, block_row), np.uint8)  # probes <= 255; the first wb of each row are the blocks'
    block_run = block_acc.reshape(-1)[:(hb - 1) * block_row + wb]
    probe_hits = np.zeros(w + LANES, np.uint8)  # of one row of cells, and past its end up to LANES
    hit_counts = np.zeros(w + LANES, np.int32)
    counts = np.zeros(maps.shape[0], np.float32)
    need = max(1, int(np.ceil(min_share * probes)))
    heap = np.empty(max(keep, 1), np.float64)
    kept = 0
    cells = maps.reshape(-1)
    row_length = maps.shape[2]
    offsets = np.empty(k, np.int64)  # each point's cell in ``cells`` when the template is at cell (0, 0)
    for t in range(n_templates):
        counts[:] = 0
        lowest, highest = len(cells), 0
        for j in range(k):
            counts[bins[t, j]] += 1
            offsets[j] = (bins[t, j] * maps.shape[1] + pad + dy[t, j]) * row_length + pad + dx[t, j]
            lowest, highest = min(lowest, offsets[j]), max(highest, offsets[j])
        # the rows' reads, LANES - 1 cells past a span's end at most, spill into the next row of the
        # maps, never past their end: the padding must outreach the templates by one row
        if lowest < 0 or highest + (h - 1) * row_length + w - 1 + LANES > len(cells):
            raise ValueError("score_templates: a template reaches past the padded maps")
        # the block pass: each probe's hb rows of wb blocks are read as one run of the flat bounds,
        # the blocks between a row's end and the next row's start counted too, never read
        block_acc[:, :] = 0
        for j in range(probes):
            b = bins[t, j]
            oy, ox = pad + dy[t, j], pad + dx[t, j]
            at = (((oy % BLOCK) * BLOCK + ox % BLOCK) * bounds.shape[2] + b) * block_plane \
                + (oy // BLOCK) * block_row + ox // BLOCK
            row = blocks[at:at + len(block_run)]
            for x in range(len(block_run)):
                block_run[x] += row[x]
        s = size_index[t]
        best = heap[0] if 0 < keep == kept else -1.0
        by, bx = -1, -1
        for y in range(h):
            if y % BLOCK == 0:  # a new row of blocks: the span of cells from its first to its last
                lo, hi = w, 0  # block worth counting cell by cell (none: empty)
                for x in range(wb):
                    if block_acc[y // BLOCK, x] >= need:
                        lo, hi = min(lo, BLOCK * x), min(BLOCK * (x + 1), w)
            if lo >= hi:
                continue
            n = (hi - lo + LANES - 1) // LANES * LANES
            line = probe_hits[lo:lo + n]
            line[:] = 0
            at = y * row_length + lo
            for j in range(probes):
                row = cells[offsets[j] + at:offsets[j] + at + n]
                for x in range(n):
                    line[x] += row[x]
            passing, first, last = 0, hi, lo  # the cells that pass, the first and the last of them
            for x in range(hi - lo):
                if line[x] >= need:
                    passing += 1
                    first = min(first, lo + x)
                    last = lo + x
            if passing == 0:
                continue
            # where many cells of that stretch go on, the rest of the points are counted along it
            # at once (vectorised adds) rather than cell by cell (scattered reads)
            dense = passing * DENSE_ROW_SHARE > last + 1 - first
            if dense:
                n = (last + 1 - first + LANES - 1) // LANES * LANES
                whole, counted = hit_counts[first:first + n], probe_hits[first:first + n]
                for x in range(n):
                    whole[x] = counted[x]
                at = y * row_length + first
                for j in range(probes, k):
                    row = cells[offsets[j] + at:offsets[j] + at + n]
                    for x in range(n):
                        whole[x] += row[x]
            for x in range(first, last + 1):
                if probe_hits[x] < need:
                    continue
                expected = 0.0
                for b in range(maps.shape[0]):
                    if counts[b] > 0:
                        expected += counts[b] * chance[s, b, y, x]
                if dense:
                    hits = np.int64(hit_counts[x])
                else:
                    # counted in chunks of ``probes`` points, given up as soon as even hits on
                    # every point left could not beat the best: the same best, far fewer reads
                    hits = np.int64(probe_hits[x])
                    at = y * row_length + x
                    j = probes
                    while j < k and hits + (k - j) - expected > best * k:
                        for i in range(j, min(j + probes, k)):
                            hits += cells[offsets[i] + at]
                        j += probes
                    if j < k:
                        continue
                score = (hits - expected) / k
                if score > best:
                    best, by, bx = score, y, x
        if by < 0:
            best = -1.0
        elif keep > 0:
            kept = _keep_largest(heap, kept, best)
        best_score[t], best_y[t], best_x[t] = best, by, bx


@njit(nogil=True, cache=True)
def rank_as_one_call(keep, best_score, best_y, best_x):
    """``score_templates``' output over consecutive chunks of templates, in place, made its
    output in one call: each chunk ranked its templates against its own ``keep``-th best so
    far, lower than one call's, so it scored templates one call gives up (-1). A template one
    call scores, a chunk scores alike (its bound is no higher), so walking the templates in
    order with one call's heap tells which to give up. Without it the stages saw a different
    set of templates with each number of workers: on the clean latency image 3 the windows
    stage found 6 places with 2 workers and 4 with 1, and 2 workers did 18 % more work."""
    heap = np.empty(max(keep, 1), np.float64)
    kept = 0
    for t in range(len(best_score)):
        if best_y[t] < 0:
            continue
        if 0 < keep == kept and not best_score[t] > heap[0]:
            best_score[t], best_y[t], best_x[t] = -1.0, -1, -1
        elif keep > 0:
            kept = _keep_largest(heap, kept, best_score[t])


#: the smallest part diameter searched within colour regions, share of the smallest region's
#: bounding-box diagonal (``TemplateSearch.sizes``)
SMALLEST_REGION_SHARE = 0.5


class TemplateSearch:
    """The search of the module doc for one aspect graph."""

    #: sets of coarse templates kept (``_coarse_templates``): the image's sizes, and the
    #: ``larger`` check's about a few places and the ``small`` generator's of its patches; the
    #: least recently used goes, so an image's one-off sets leave the image's sizes kept
    KEPT_TEMPLATE_SETS = 4

    def __init__(self, graph: AspectGraph, p: SearchParams):
        self.graph = graph
        self.library = TemplateLibrary(graph, p)
        self._templates: dict[tuple, tuple[np.ndarray, ...]] = {}
        self._last_turned: tuple[tuple, tuple[np.ndarray, ...]] | None = None
        self.warm()

    @staticmethod
    def library_changes(old: SearchParams, new: SearchParams) -> bool:
        """Whether the templates must be derived again for the new parameters."""
        return (old.template_points, old.coarse_view_step_deg) != (new.template_points, new.coarse_view_step_deg)

    def warm(self) -> None:
        """Compile (or load from numba's cache) the kernels now, not on the first image."""
        maps = np.zeros((BINS, 3, 3), np.uint8)
        one = np.zeros((1, 1), np.int16)
        out = np.zeros(1), np.zeros(1, np.int64), np.zeros(1, np.int64)
        score_templates(maps, block_bounds(maps), 1, one, one, one.astype(np.uint8), np.zeros(1, np.int64),
                        np.zeros((1, BINS, 1, 1), np.float32), 1, 0.5, 1, *out)
        rank_as_one_call(1, *out)

    def sizes(self, frame: Frame, p: SearchParams, distances: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
        """The part diameters in pixels the search tries (geometric steps): between the
        parameters' shares of the image diagonal, or the sizes the frame's regions allow
        (``Frame.region_extents``, the part's colour regions), or, for each end of ``distances``
        (the part's model centre nearest and farthest from the camera, metres; 0: unknown)
        that is known, the part's diameter at that distance."""
        diagonal = np.hypot(frame.camera.width, frame.camera.height)
        low, high = p.min_size_fraction * diagonal, p.max_size_fraction * diagonal
        nearest, farthest = distances
        at_one_metre = frame.camera.focal * self.library.diameter
        # within the sizes the fractions may name: a distance of millimetres would otherwise
        # ask for templates, and maps padded for them, of many thousands of pixels
        smallest = field_ranges()["search.min_size_fraction"][0] * diagonal
        largest = field_ranges()["search.max_size_fraction"][1] * diagonal
        regions = frame.region_extents
        if regions is not None and len(regions):
            # the part's outline lies within one region, so even its narrowest view spans no
            # more than the largest region's diagonal; a region holding the part alone is at
            # most about 1.4 times the part's span plus its margin across, so a part alone in
            # the smallest region is at least half its diagonal (LM-O's parts are 65-190 px
            # where the fractions' smallest is 160 px: docs/results/real_lmo.md). Only ever
            # lowered: a grey part shares one region, most of the image, with the desk
            low = max(min(low, SMALLEST_REGION_SHARE * regions.min()), smallest)
            high = min(high, regions.max() / self.library.narrowest_span_share)
        if farthest > 0:
            low = np.clip(at_one_metre / farthest, smallest, largest)
        if nearest > 0:
            high = np.clip(at_one_metre / nearest, smallest, largest)
        low = min(low, high)  # one end known and beyond the other's default
        count = max(1, int(np.ceil(np.log(high / low) / np.log(p.size_step))) + 1)
        return low * p.size_step ** np.arange(count)

    def templates(self, views: np.ndarray, angles: np.ndarray, sizes: np.ndarray, factor: int):
        """Offsets (T, K) in coarse cells and direction bins of every (view, angle, size),
        in that nesting order."""
        lib = self.library
        rx, ry, bins = self._turned(views, angles)
        scale = sizes / lib.diameter / factor  # coarse cells per metre
        dx = np.rint(rx[:, :, None] * scale[None, None, :, None]).astype(np.int16)  # (V, A, S, K)
        dy = np.rint(ry[:, :, None] * scale[None, None, :, None]).astype(np.int16)
        bins = np.broadcast_to(bins[:, :, None], dx.shape)
        k = lib.n_points
        return dx.reshape(-1, k), dy.reshape(-1, k), np.ascontiguousarray(bins).reshape(-1, k)

    def _turned(self, views: np.ndarray, angles: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The views' template points turned by each angle, x and y (V, A, K) in metres, and
        their direction bins (V, A, K): the same at every size, kept for the last views and
        angles (half the cost of a patch's ``templates``, each patch having sizes of its own)."""
        key = (views.tobytes(), angles.tobytes())
        last = self._last_turned
        if last is None or last[0] != key:
            lib = self.library
            c, s = np.cos(angles), np.sin(angles)
            pts = lib.points[views]  # (V, K, 2)
            rx = pts[:, None, :, 0] * c[None, :, None] - pts[:, None, :, 1] * s[None, :, None]
            ry = pts[:, None, :, 0] * s[None, :, None] + pts[:, None, :, 1] * c[None, :, None]
            direction = np.mod(lib.angles[views][:, None, :] + angles[None, :, None], np.pi)
            last = self._last_turned = key, (rx, ry, (direction / np.pi * BINS).astype(np.uint8) % BINS)
        return last[1]

    def _coarse_templates(self, angle_count: int, sizes: np.ndarray, factor: int) -> tuple[np.ndarray, ...]:
        """``templates`` of the coarse views at ``angle_count`` in-plane angles and each
        template's view, angle, size and size index, read-only; kept for the next image (the
        same camera and parameters give the same templates: 5 ms of each image's search)."""
        key = (angle_count, factor, sizes.tobytes())
        if key in self._templates:
            self._templates[key] = self._templates.pop(key)  # the most recently used last
        else:
            if len(self._templates) >= self.KEPT_TEMPLATE_SETS:
                del self._templates[next(iter(self._templates))]
            views = self.library.coarse_views
            angles = np.arange(angle_count) * (2 * np.pi / angle_count)
            arrays = (*self.templates(views, angles, sizes, factor), np.repeat(views, len(angles) * len(sizes)),
                      np.tile(np.repeat(angles, len(sizes)), len(views)), np.tile(sizes, len(views) * len(angles)),
                      np.tile(np.arange(len(sizes)), len(views) * len(angles)))
            self._templates[key] = arrays
        return self._templates[key]

    def coarse(self, frame: Frame, p: SearchParams, pool: WorkerPool = SERIAL, sizes: np.ndarray | None = None,
               box: tuple[int, int, int, int] | None = None,
               distances: tuple[float, float] = (0.0, 0.0)) -> "CoarseResult":
        """Every coarse template's best score and position in the image (module doc, step 3);
        the templates are split into one chunk per worker thread (the kernel releases the GIL).
        ``sizes`` (pixels, ascending) replace those of the parameters and ``distances``
        (``sizes``), and ``box`` (x0, y0, x1, y1 pixels) keeps only its edge pixels: a search
        about one place (``larger``)."""
        lib = self.library
        factor = p.coarse_factor
        sizes = self.sizes(frame, p, distances) if sizes is None else sizes
        # the maps' padding outreaches every template point by a row (``score_templates``)
        pad = int(np.ceil(sizes[-1] / factor * max(0.5, lib.reach_share))) + p.spread + 1
        maps = ResponseMaps.of(frame.evidence, factor, p.spread, pad, box, pool)
        chance = maps.chances([max(3, int(round(d / factor)) | 1) for d in sizes], pool)
        dx, dy, bins, view, angle, size, size_index = self._coarse_templates(p.angles, sizes, factor)
        n = len(dx)
        result = CoarseResult(score=np.full(n, -1.0), y=np.zeros(n, np.int64), x=np.zeros(n, np.int64), view=view,
                              angle=angle, size=size, size_index=size_index, factor=factor)

        def run(chunk: slice) -> None:
            score_templates(maps.maps, maps.bounds, pad, dx[chunk], dy[chunk], bins[chunk], result.size_index[chunk],
                            chance, lib.n_points // PROBE_STRIDE, probe_share(maps, p), ranked_templates(p),
                            result.score[chunk], result.y[chunk], result.x[chunk])

        chunks = pool.split(n)
        pool.map(run, chunks)
        if len(chunks) > 1:
            rank_as_one_call(ranked_templates(p), result.score, result.y, result.x)
        found = result.y >= 0
        result.y[found] += maps.origin[0]
        result.x[found] += maps.origin[1]
        return result

    def hypotheses(self, frame: Frame, p: SearchParams, pool: WorkerPool = SERIAL) -> list[Hypothesis]:
        """The best distinct templates of the image as hypotheses (module doc)."""
        return self.best(self.coarse(frame, p, pool), frame, p.hypotheses, p)

    def best(self, c: "CoarseResult", frame: Frame, count: int, p: SearchParams) -> list[Hypothesis]:
        """The ``count`` best distinct templates of a coarse result as hypotheses."""
        order = np.argsort(-c.score)
        order = order[c.score[order] > 0]
        center_x, center_y = c.center_px()
        # a template is a duplicate of a better one of the same view, about one angle step
        # turned, about one position; other views at one position are kept: several views
        # fit a part's position, and the best by the coarse score is often not the right one
        step = 2 * np.pi / p.angles
        kept: list[int] = []
        of_view: dict[int, list[int]] = {}  # the kept templates of each view: only those can be duplicates
        for t, view in zip(order.tolist(), c.view[order].tolist()):
            if len(kept) == count:
                break
            if not any(abs(np.angle(np.exp(1j * (c.angle[u] - c.angle[t])))) <= step
                       and np.hypot(center_x[u] - center_x[t], center_y[u] - center_y[t])
                       < p.distinct_fraction * c.size[t] for u in of_view.get(view, ())):
                kept.append(t)
                of_view.setdefault(view, []).append(t)
        centers_n = frame.camera.undistort(np.stack([center_x[kept], center_y[kept]], axis=1))
        out = []
        for t, center_n in zip(kept, centers_n):
            scale = c.size[t] / self.library.diameter / frame.camera.focal  # 1 / depth
            out.append(Hypothesis(_seed_region(virtual_alignment(center_n)), int(c.view[t]), float(scale),
                                  float(c.angle[t]), np.zeros(2), float(c.score[t])))
        return out

    @staticmethod
    def places(c: "CoarseResult", count: int) -> list[tuple[np.ndarray, float]]:
        """The ``count`` best places of a coarse result, (centre in pixels, part diameter in
        pixels), whatever the view: a template's place counts once another's lies within half
        the smaller of their sizes."""
        order = np.argsort(-c.score)
        order = order[c.score[order] > 0]
        x, y = c.center_px()
        x, y, size = x[order], y[order], c.size[order]
        # each place kept rules out every template near it at once: template by template
        # against the kept places, in Python, took 5-8 ms of a clean image reaching the windows
        free = np.arange(len(order))  # the templates no kept place rules out, best first
        kept: list[int] = []
        while len(kept) < count and len(free):
            kept.append(k := int(free[0]))
            free = free[np.hypot(x[k] - x[free], y[k] - y[free]) >= 0.5 * np.minimum(size[k], size[free])]
        return [(np.array([x[k], y[k]]), float(size[k])) for k in kept]


@dataclass
class CoarseResult:
    """Per coarse template: its view, in-plane angle (radians), part diameter (pixels), and
    its best score and cell."""

    score: np.ndarray
    y: np.ndarray
    x: np.ndarray
    view: np.ndarray
    angle: np.ndarray
    size: np.ndarray
    size_index: np.ndarray
    factor: int

    def center_px(self) -> tuple[np.ndarray, np.ndarray]:
        """The templates' best positions in pixels (the centres of their cells)."""
        half = (self.factor - 1) / 2.0
        return self.x * self.factor + half, self.y * self.factor + half


def probe_share(maps: ResponseMaps, p: SearchParams) -> float:
    """The share of a template's probe points that must hit for a position to be counted
    further: ``min_coarse_share``, or on maps so dense that random points hit nearly that
    often (texture) their density plus ``CHANCE_MARGIN``."""
    hc, wc = maps.shape
    image_cells = np.prod(maps.image_shape)  # a box's maps: the whole image's density
    density = float(np.count_nonzero(maps.maps[:, maps.pad:maps.pad + hc, maps.pad:maps.pad + wc])) \
        / (maps.maps.shape[0] * image_cells)
    return max(p.min_coarse_share, density + CHANCE_MARGIN)


def ranked_templates(p: SearchParams) -> int:
    """How many of the best coarse templates the kernel ranks exactly: 8 times as many as the
    most a stage takes (the seeds' 128 distinct templates lay within the best 157-332 of
    10,080 on the bench images, docs/DECISIONS.md); the rest are given up early."""
    return 8 * max(p.seeds, p.hypotheses, p.windows)


def _seed_region(R_align: np.ndarray) -> Region:
    """The virtual camera of a template's centre, as the region the refinement needs."""
    return Region(R_align=R_align, center=np.zeros(2), scale=1.0, features=None, orientation_histogram=None,
                  distance_maps=None)


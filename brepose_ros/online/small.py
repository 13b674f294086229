"""The small-part generator: template sizes below the search's, only where the image's edges
form a patch that small.

The template search (``search``) tries part diameters from ``search.min_size_fraction`` of
the image diagonal (160 px at 640 x 480) up: lowering that for every image fits small
templates onto pieces of larger objects and of the part itself among clutter and occluders
(``min_size_fraction`` 0.1 on the bench's small images: 2 right poses more, 3 lost to such
pieces, docs/results/small.md). A part far from the camera shows as a compact patch of
edges, a cluster of touching segments (``regions.region_groups``) or the whole image's
edges on a plain background, narrower than the smallest template. Only there, and only at
the sizes that patch allows, are smaller templates slid: the part's diameter is at least
the patch's widest span (the part covers its own edges) and at most that span over the
narrowest view's span share (``TemplateLibrary.narrowest_span_share``). The search's best
templates of each patch then seed the bipartite matching as the ``seeded`` generator's do.

A patch the regular sizes cover is left to them, and so is a patch among longer edges of
other objects (``ISOLATION_SHARE``), so an image whose edges all spread wider costs nothing;
a patch costs one template search over its own box at a few sizes.
"""
from __future__ import annotations

import numpy as np

from ..params import SearchParams
from .frame import Frame
from .hypotheses import Hypothesis
from .search import TemplateSearch, widest_span
from .workers import SERIAL, WorkerPool

#: the box searched about a patch reaches this share of the largest size tried past the
#: patch's end points each way: the part's centre lies inside its own edges' hull, give or
#: take a view whose edges crowd to one side
BOX_MARGIN = 0.5
#: the best distinct templates of a patch matched as seeds: a patch is a few hundred cells,
#: where the whole image's ``search.seeds`` (128) would mostly repeat one place
SEEDS_PER_PATCH = 32
#: a patch is searched only if the other segments in its box are at most this share of its own
#: edge length: a patch among longer edges is a piece of a larger object (on the bench a hole's
#: ring inside a bracket 4x its size, where a small pose outscored the whole part), while a
#: part far from the camera lies alone or among a few short edges of its background
ISOLATION_SHARE = 0.25


def patch_sizes(span: float, smallest_searched: float, narrowest_share: float, smallest_pose: float,
                step: float) -> np.ndarray:
    """The part diameters, pixels, worth trying on a patch of edges ``span`` pixels across:
    from the span (a part is no smaller than its own edges) to the span over the narrowest
    view's share of the diameter (a part seen from its narrowest side), in even geometric
    steps of at most ``step``, no smaller than ``smallest_pose`` (a pose that small scores 0)
    and below the sizes the regular search's smallest covers (within half a step of it).
    Empty when the regular sizes cover the patch."""
    low = max(span, smallest_pose)
    high = min(span / max(narrowest_share, 1e-6), largest_patch_size(smallest_searched, step))
    if high < low:
        return np.zeros(0)
    return np.geomspace(low, high, int(np.ceil(np.log(high / low) / np.log(step))) + 1)


def largest_patch_size(smallest_searched: float, step: float) -> float:
    """The largest part diameter, pixels, ``patch_sizes`` tries: half a step below the regular
    search's smallest size."""
    return smallest_searched / np.sqrt(step)


def small_part_seeds(frame: Frame, groups: list[np.ndarray], p: SearchParams, search: TemplateSearch,
                     smallest_pose: float, distances: tuple[float, float] = (0.0, 0.0),
                     pool: WorkerPool = SERIAL) -> list[Hypothesis]:
    """The best distinct templates (``SEEDS_PER_PATCH`` per patch) of every patch of edges
    narrower than the regular search's smallest size (module doc): ``groups`` are the segment
    indices of the image's regions (``regions.region_groups``). None where the working range
    ``distances`` is known: the regular search then tries the part's sizes in it."""
    if distances != (0.0, 0.0):
        return []
    regular = search.sizes(frame, p)
    h, w = frame.evidence.shape
    middles = frame.segments_px.mean(axis=1)
    lengths = np.linalg.norm(frame.segments_px[:, 1] - frame.segments_px[:, 0], axis=1)
    largest = largest_patch_size(regular[0], p.size_step)
    seeds: list[Hypothesis] = []
    done: set[tuple[int, int, int, int]] = set()
    for indices in groups:
        ends = frame.segments_px[indices].reshape(-1, 2)
        if np.ptp(ends, axis=0).max() > largest:
            continue  # wider than any size ``patch_sizes`` allows, its widest span (K^2) not needed
        sizes = patch_sizes(widest_span(ends), regular[0], search.library.narrowest_span_share, smallest_pose,
                            p.size_step)
        if not len(sizes):
            continue
        reach = BOX_MARGIN * sizes[-1]
        x0, y0 = np.clip(np.floor(ends.min(axis=0) - reach), 0, [w, h]).astype(int)
        x1, y1 = np.clip(np.ceil(ends.max(axis=0) + reach), 0, [w, h]).astype(int)
        if (x0, y0, x1, y1) in done:  # the whole image's edges may be its one cluster
            continue
        done.add((x0, y0, x1, y1))
        inside = np.all((middles >= [x0, y0]) & (middles <= [x1, y1]), axis=1)
        inside[indices] = False
        if lengths[inside].sum() > ISOLATION_SHARE * lengths[indices].sum():
            continue
        coarse = search.coarse(frame, p, pool, sizes=sizes, box=(x0, y0, x1, y1))
        seeds += search.best(coarse, frame, SEEDS_PER_PATCH, p)
    return seeds

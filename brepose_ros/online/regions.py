"""Candidate regions of an image, each seen by its virtual camera and normalised as the
views of the aspect graph are (``metric_space.outline_normalisation``).

The whole image is one region; clusters of touching segments are the others, the
candidate positions of an off-centre part among clutter. A region is turned onto the
virtual camera centred on it (``camera.virtual_alignment``), where the part looks like an
orthographic view scaled by 1 / depth, and normalised there.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import to_virtual, virtual_alignment
from ..metric_space import outline_normalisation, segment_lengths
from ..params import MatchParams
from . import matching
from .frame import Frame
from .lines2d import convex_hull
from .prefilter import ChamferPrefilter, orientation_histogram

#: fewer segments than this cannot pin down a view, in a region or in a whole image
MIN_REGION_SEGMENTS = 4

#: a region's edge pixels are those inside the convex hull of its segments grown by this
#: factor: rounded outlines and corners, which give no segment, bulge out of that hull
REGION_GROWTH = 1.15

@dataclass
class Region:
    """Image segments of one candidate region, seen by the virtual camera centred on it."""

    R_align: np.ndarray
    center: np.ndarray  # normalisation in virtual normalised coordinates
    scale: float
    features: matching.SegmentFeatures
    orientation_histogram: np.ndarray  # of the normalised segments (``prefilter``)
    distance_maps: np.ndarray  # oriented distance maps of its edge pixels for the chamfer pre-filter


def region_groups(frame: Frame, p: MatchParams) -> list[np.ndarray]:
    """Segment indices of the candidate regions: the whole image, then clusters of
    touching segments (off-centre part among clutter)."""
    groups = [np.arange(len(frame.segments_px))]
    groups += cluster_segments(frame.segments_px,
                               gap=p.cluster_gap_fraction * np.hypot(frame.camera.width, frame.camera.height))
    return [g for g in groups[:p.max_regions] if len(g) >= MIN_REGION_SEGMENTS]


def segments_within(frame: Frame, center_px: np.ndarray, radius_px: float) -> np.ndarray:
    """Indices of the segments whose midpoints lie within ``radius_px`` of ``center_px``: the
    window about a place the template search found (``search``)."""
    return np.nonzero(segment_windows(frame, np.reshape(center_px, (1, 2)), np.array([radius_px]))[0])[0]


def segment_windows(frame: Frame, centers_px: np.ndarray, radii_px: np.ndarray) -> np.ndarray:
    """(K, N) masks of ``segments_within`` for K centres (K, 2) and radii (K,) at once."""
    middle = frame.segments_px.mean(axis=1)
    return (np.hypot(middle[:, 0] - centers_px[:, :1], middle[:, 1] - centers_px[:, 1:])
            < np.asarray(radii_px)[:, None])


def normalised_region(indices: np.ndarray, frame: Frame, p: MatchParams) -> Region | None:
    """The region's longest segments on the virtual camera centred on them, normalised; and
    the pre-filter's distance maps of the edge pixels around them, normalised alike. None
    when there are fewer than ``MIN_REGION_SEGMENTS`` or they cannot be normalised (all on
    one line or point)."""
    if len(indices) < MIN_REGION_SEGMENTS:
        return None
    indices = indices[matching.longest(frame.segments_n[indices], p.max_image_segments)]
    try:
        center = outline_normalisation(frame.segments_n[indices]).center
        R_align = virtual_alignment(center)
        virtual = to_virtual(frame.segments_n[indices], R_align)
        norm = outline_normalisation(virtual)
    except ValueError:
        return None
    features = matching.describe(norm.apply(virtual))
    around = edge_pixels_around(frame, frame.segments_px[indices])
    pixels = norm.apply(to_virtual(frame.edge_points_n[around], R_align))
    return Region(R_align=R_align, center=norm.center, scale=norm.scale, features=features,
                  orientation_histogram=orientation_histogram(features.orientations, features.lengths),
                  distance_maps=ChamferPrefilter.distance_maps(pixels, frame.evidence.directions[around]))


def edge_pixels_around(frame: Frame, segments_px: np.ndarray) -> np.ndarray:
    """Mask of the frame's edge pixels inside the segments' convex hull grown by
    ``REGION_GROWTH`` about its centre."""
    hull = convex_hull(segments_px)
    center = hull.mean(axis=0)
    hull = center + REGION_GROWTH * (hull - center)
    x0, y0 = np.floor(hull.min(axis=0)).astype(int)
    x1, y1 = np.ceil(hull.max(axis=0)).astype(int) + 1
    mask = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull - [x0, y0]).astype(np.int32), 1)
    pixels = frame.evidence.pixels
    x, y = pixels[:, 0] - x0, pixels[:, 1] - y0
    inside = (x >= 0) & (x < x1 - x0) & (y >= 0) & (y < y1 - y0)
    inside[inside] = mask[y[inside], x[inside]] > 0
    return inside


def cluster_segments(segments_px: np.ndarray, gap: float) -> list[np.ndarray]:
    """Groups of segments chained by end points closer than ``gap``, largest first.

    Only groups with at least a tenth of the largest group's total length are returned:
    these are the candidate positions of an off-centre part among clutter.
    """
    n = len(segments_px)
    ends = segments_px.reshape(-1, 2)
    # the end points' distances as np.linalg.norm forms them (the root of dx^2 + dy^2), without
    # its (2N, 2N, 2) differences: 200 segments took 10 ms that way
    dx, dy = ends[:, None, 0] - ends[None, :, 0], ends[:, None, 1] - ends[None, :, 1]
    close = np.sqrt(dx * dx + dy * dy) < gap
    # two segments link when any end of one is close to any end of the other (ends 2k, 2k + 1)
    linked = close[0::2, 0::2] | close[0::2, 1::2] | close[1::2, 0::2] | close[1::2, 1::2]
    parent = list(range(n))  # Python ints: the union-find on numpy scalars took 4 ms at 200 pairs

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(*(k.tolist() for k in np.nonzero(np.triu(linked, 1)))):
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

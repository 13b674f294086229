"""The image edge stage (seed paper, section 5): straight line segments of a camera image.

The part is grey metal without texture, so its only reliable features are the straight
boundaries of its faces. The paper finds them with Canny and a "modified Hough" transform
and merges the pieces of one edge by nearest-neighbour clustering under a contiguity rule
(end points close) and a continuity rule (collinear). Here that is:

1. grayscale, float32 on the 0..255 scale (uint16 keeps its finer steps);
2. Gaussian blur, then Canny with thresholds set from the image's own gradient noise, so
   that a dim, low-contrast photograph and a bright one give the same edges; on a colour
   image (``edges.colour``) the gradient of the luminance or of an opponent-colour plane,
   whichever stands out more above its own noise (:func:`colour_gradients`), so that a
   part of the background's brightness and another hue keeps its outline;
3. ``cv2.HoughLinesP``, which yields broken and duplicated pieces of every edge;
4. :func:`merge_segments`: one segment per edge, on the pieces' length-weighted line;
5. :func:`refine_segments`: every segment refitted to, and extended over, the Canny pixels
   along it (Hough end points are quantised and Hough loses the ends of edges), then
   merged again.

``detector="lsd"`` replaces steps 2, 3 and 5 by OpenCV's LSD detector. The default stays
the paper's Canny + Hough: as accurate on the test scenes, and it still finds faint edges
where LSD's fixed gradient threshold finds none (docs/DECISIONS.md).

Coordinates are pixels, x right, y down, pixel centres at integer coordinates.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from ..params import EdgeParams
from .kernels import connected_labels, edge_runs_kernel, median_of_every_other, scaled_int16

#: median / scale of a Rayleigh distribution: the gradient magnitude of pure Gaussian noise
_RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))
#: an edge pixel runs along a line when its direction is this close to the line's, degrees:
#: the score's direction bin, over which Sobel directions on a blurred edge scatter
_ALONG_DEG = 22.5
#: Canny takes int16 derivatives; scaling the float Sobel output keeps sub-grey-level steps
#: (3x3 Sobel of a 0..255 image stays within +-1020, times 16 within int16)
_DERIVATIVE_SCALE = 16.0


@dataclass
class ImageEdges:
    """What the edge stage found in one image: the gray image, the gradient Canny ran on,
    Canny's edge pixels and the merged line segments (N, 2, 2), longest first, those of the
    search and those of the pose refinement (``refinement_params``). Later stages score
    poses on the pixels and their gradient directions."""

    gray: np.ndarray
    gradient_x: np.ndarray  # float32 Sobel derivatives of the blurred gray image (colour_gradients')
    gradient_y: np.ndarray
    edge_map: np.ndarray
    segments: np.ndarray
    refine_segments: np.ndarray


def detect_edges(image: np.ndarray, params: EdgeParams = EdgeParams()) -> ImageEdges:
    """Canny edge pixels and merged straight line segments of an image.

    ``image`` is uint8 or uint16 (float is read on the uint8 scale), gray (H, W) or
    (H, W, 1), BGR or BGRA (H, W, 3|4); anything else, an empty image or NaN/inf raise
    ValueError. A constant image has no edges and gives (0, 2, 2) segments.
    """
    pixels, (segments, refine_segments) = finished_without_background(
        edge_pixels(image, params), params,
        lambda pixels: (line_segments(pixels, params), line_segments(pixels, refinement_params(params))))
    return dataclasses.replace(pixels, segments=segments, refine_segments=refine_segments)


def finished_without_background(pixels: ImageEdges, params: EdgeParams,
                                finish: Callable[[ImageEdges], tuple]) -> tuple[ImageEdges, tuple]:
    """``pixels`` and ``finish(pixels)`` (whose first item is the search's line segments), or,
    where those segments show a background's pattern of long lines (:func:`without_background`,
    rare), the pixels without it and everything finished again on them."""
    finished = finish(pixels)
    cleared = without_background(pixels, finished[0], params)
    return (pixels, finished) if cleared is pixels else (cleared, finish(cleared))


def refinement_params(params: EdgeParams) -> EdgeParams:
    """The edge parameters of the segments the pose refinement pairs with: longer raw pieces."""
    return dataclasses.replace(params, raw_min_length_fraction=params.refine_raw_min_length_fraction)


def edge_pixels(image: np.ndarray, params: EdgeParams) -> ImageEdges:
    """The first half of :func:`detect_edges`: the gray image, its gradient and Canny's edge
    pixels, no segments yet (the estimator prepares the scoring from them meanwhile)."""
    gray = to_gray(image)
    if gray.max() == gray.min():
        flat = np.zeros(gray.shape, np.float32)
        return ImageEdges(gray, flat, flat, np.zeros(gray.shape, np.uint8), np.zeros((0, 2, 2)),
                          np.zeros((0, 2, 2)))
    if params.colour and is_colour_image(image):
        dx, dy, thresholds = colour_gradients(image, gray, params)
    else:
        (dx, dy), thresholds = gradients(gray, params), None  # canny_from_gradients' adaptive ones
    return ImageEdges(gray, dx, dy, canny_from_gradients(dx, dy, params, thresholds), np.zeros((0, 2, 2)),
                      np.zeros((0, 2, 2)))


def line_segments(pixels: ImageEdges, params: EdgeParams) -> np.ndarray:
    """The second half of :func:`detect_edges`: the merged segments (N, 2, 2) of
    :func:`edge_pixels`' result, longest first."""
    gray, edges = pixels.gray, pixels.edge_map
    if params.detector == "lsd":
        merged = merge_segments(lsd_segments(gray, params), params)
    else:
        merged = merge_segments(hough_segments(edges, params), params)
        if params.refine:
            merged = merge_segments(refine_segments(merged, edges, params), params)
    lengths = np.linalg.norm(merged[:, 1] - merged[:, 0], axis=1)
    merged = merged[lengths >= params.min_length_fraction * float(np.hypot(*gray.shape))]
    return merged[: params.max_segments]


def background_segments(segments: np.ndarray, diagonal: float, params: EdgeParams) -> np.ndarray:
    """Those of the merged ``segments`` (K, 2, 2) that lie on a straight line whose pieces
    reach, from the first to the last, across at least ``background_line_fraction`` of the
    image ``diagonal`` and add up to at least half of that, one of ``background_pattern_lines``
    or more such lines running parallel (within ``merge_angle_deg``): a table's seams, tiles
    or slats cross the frame in rows, broken where something stands in front, and no part in
    view has that many edges that long (a rod's or a grained surface's few are left alone).
    Pieces are collinear as :func:`merge_segments` joins them, but across any gap."""
    segments = np.asarray(segments, np.float64).reshape(-1, 2, 2)
    lengths = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)
    bound = params.background_line_fraction * diagonal
    if params.background_line_fraction <= 0 or lengths.sum() < bound / 2:
        return np.zeros((0, 2, 2))
    segments, lengths = segments[lengths > 0], lengths[lengths > 0]
    unit = (segments[:, 1] - segments[:, 0]) / lengths[:, None]
    tolerance = np.minimum(np.deg2rad(params.merge_angle_deg) + np.arctan(1.0 / lengths), np.pi / 2)
    i, j = _candidate_pairs(np.arctan2(unit[:, 1], unit[:, 0]) % np.pi, tolerance + tolerance.max())
    longer = np.where(lengths[i] >= lengths[j], i, j)
    shorter = i + j - longer
    joins = _joins(segments[shorter], unit[shorter], np.sin(tolerance[shorter]), segments[longer, 0], unit[longer],
                   -np.inf, np.inf, params)
    groups, label = connected_labels(len(segments), i[joins], j[joins])
    centre, axis = _fit_lines(label, groups, segments.mean(axis=1), lengths, unit)
    lo, hi = _spans(label, groups, ((segments - centre[label][:, None]) * axis[label][:, None]).sum(axis=-1))
    long = np.flatnonzero((hi - lo >= bound) & (np.bincount(label, lengths, minlength=groups) >= bound / 2))
    direction = np.arctan2(axis[long, 1], axis[long, 0])
    parallel = np.abs(np.sin(direction[:, None] - direction[None, :])) <= np.sin(np.deg2rad(params.merge_angle_deg))
    pattern = np.zeros(groups, bool)
    pattern[long[parallel.sum(axis=1) >= params.background_pattern_lines]] = True
    return segments[pattern[label]]


def without_background(pixels: ImageEdges, segments: np.ndarray, params: EdgeParams) -> ImageEdges:
    """``pixels`` without the edge pixels that run along one of the :func:`background_segments`
    of its ``segments`` (within ``merge_distance`` of it, turned from it by less than
    ``_ALONG_DEG``: an edge that meets or crosses it keeps its pixels): the same object when
    there are none."""
    shape = pixels.edge_map.shape
    lines = background_segments(segments, float(np.hypot(*shape)), params)
    if not len(lines):
        return pixels
    label = np.zeros(shape, np.int32)  # 1 + the segment drawn last over a pixel (lines cross at a few)
    width = int(round(2 * params.merge_distance)) + 1
    for k, (a, b) in enumerate(np.rint(lines).astype(int)):
        cv2.line(label, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), k + 1, width)
    rows, cols = np.nonzero(pixels.edge_map)
    line = label[rows, cols] - 1
    rows, cols, line = rows[line >= 0], cols[line >= 0], line[line >= 0]
    # the direction the edge runs in, as EdgeEvidence's (across the gradient)
    direction = np.arctan2(pixels.gradient_y[rows, cols], pixels.gradient_x[rows, cols]) + np.pi / 2
    d = lines[line, 1] - lines[line, 0]
    along = np.abs(np.sin(direction - np.arctan2(d[:, 1], d[:, 0]))) <= np.sin(np.radians(_ALONG_DEG))
    edge_map = pixels.edge_map.copy()
    edge_map[rows[along], cols[along]] = 0
    return dataclasses.replace(pixels, edge_map=edge_map)


def extract_segments(image: np.ndarray, params: EdgeParams = EdgeParams()) -> np.ndarray:
    """Merged straight line segments (N, 2, 2) float64 of an image, longest first."""
    return detect_edges(image, params).segments


def to_gray(image: np.ndarray) -> np.ndarray:
    """Validated float32 gray image on the 0..255 scale; ValueError says what is wrong."""
    image = np.asarray(image)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must be (H, W) or (H, W, C), got shape {image.shape}")
    if image.size == 0:
        raise ValueError(f"image is empty, shape {image.shape}")
    channels = 1 if image.ndim == 2 else image.shape[2]
    if channels not in (1, 3, 4):
        raise ValueError(f"image must have 1, 3 (BGR) or 4 (BGRA) channels, got {channels}")
    if image.dtype == np.uint8:
        gray = image.astype(np.float32)
    elif image.dtype == np.uint16:
        gray = image.astype(np.float32) / 257.0
    elif np.issubdtype(image.dtype, np.floating):
        if not np.all(np.isfinite(image)):
            raise ValueError("image contains NaN or infinite values")
        gray = image.astype(np.float32)
    else:
        raise ValueError(f"image dtype must be uint8, uint16 or float, got {image.dtype}")
    if channels == 3:
        gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
    elif channels == 4:
        gray = cv2.cvtColor(gray, cv2.COLOR_BGRA2GRAY)
    return gray.reshape(image.shape[:2])


def canny_thresholds(magnitude: np.ndarray, params: EdgeParams) -> tuple[float, float]:
    """(low, high) Canny thresholds on the Sobel magnitude scale, from the image's own noise.

    Most pixels of an image of a part lie on flat faces, where the gradient is noise whose
    magnitude is Rayleigh distributed; its median therefore measures the noise, and a high
    threshold of a few noise units keeps edges that stand out of it however faint. A
    percentile of the magnitude would not do: it marks a fixed share of pixels as edges
    even in a blank image. Every other row and column is plenty for the median and makes
    it three times faster; a compiled selection (``kernels.median_of_every_other``) four
    times more.
    """
    noise = float(median_of_every_other(np.ascontiguousarray(magnitude, np.float32))) / _RAYLEIGH_MEDIAN
    high = max(params.canny_noise_factor * noise, params.canny_min_high)
    return params.canny_low_ratio * high, high


def gradients(gray: np.ndarray, params: EdgeParams) -> tuple[np.ndarray, np.ndarray]:
    """Sobel derivatives (x, y), float32, of a :func:`to_gray` image after the blur."""
    if params.blur_size > 1:
        gray = cv2.GaussianBlur(gray, (params.blur_size, params.blur_size), params.blur_sigma)
    return cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)


def colour_gradients(image: np.ndarray, gray: np.ndarray, params: EdgeParams
                     ) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """Sobel derivatives (x, y) of a BGR(A) image and the (low, high) Canny thresholds for them.

    At each pixel the derivatives of the plane that stands out most above its own Canny
    threshold, among the luminance (``gray``) and two opponent-colour planes, red - green
    and (red + green) / 2 - blue: a coloured part on a background of like brightness (a
    yellow duck on a light board) has a hue edge that the grey image averages away. Each
    plane's derivatives are scaled by the luminance's high threshold over its own (each from
    its own noise, ``canny_thresholds``), and Canny runs at the luminance's thresholds: it
    keeps every edge of the grey image and adds the hue edges that stand as far out of the
    hue planes' noise. (The strongest of the raw B, G and R gradients instead raised the
    adaptive threshold, each channel being noisier than their mean, and lost edges of the
    grey image on the LM-O photos: docs/results/real_lmo.md.)
    """
    blue, green, red = (to_gray(np.ascontiguousarray(image[:, :, c])) for c in range(3))
    planes = [gradients(plane, params) for plane in (gray, red - green, 0.5 * (red + green) - blue)]
    thresholds = [canny_thresholds(cv2.magnitude(dx, dy), params) for dx, dy in planes]
    dx, dy = planes[0]
    strongest = cv2.magnitude(dx, dy)
    # OpenCV's masked copies, six times faster here than numpy's argmax over stacked planes
    for (hue_dx, hue_dy), (_, high) in zip(planes[1:], thresholds[1:]):
        gain = np.float32(thresholds[0][1] / high)
        hue_dx, hue_dy = hue_dx * gain, hue_dy * gain
        magnitude = cv2.magnitude(hue_dx, hue_dy)
        stronger = cv2.compare(magnitude, strongest, cv2.CMP_GT)
        strongest = cv2.max(strongest, magnitude)
        cv2.copyTo(hue_dx, stronger, dx)
        cv2.copyTo(hue_dy, stronger, dy)
    return dx, dy, thresholds[0]


def is_colour_image(image: np.ndarray) -> bool:
    """Three or four channels that are not all equal (a grey picture stored as BGR is grey)."""
    if image.ndim != 3 or image.shape[2] < 3:
        return False
    return not (np.array_equal(image[:, :, 0], image[:, :, 1]) and np.array_equal(image[:, :, 1], image[:, :, 2]))


def canny_edges(gray: np.ndarray, params: EdgeParams) -> np.ndarray:
    """uint8 edge map (255 on edges) of a :func:`to_gray` image: blur, then adaptive Canny."""
    return canny_from_gradients(*gradients(gray, params), params)


def canny_from_gradients(dx: np.ndarray, dy: np.ndarray, params: EdgeParams,
                         thresholds: tuple[float, float] | None = None) -> np.ndarray:
    """Canny on the derivatives of ``gradients`` at the (low, high) ``thresholds``, by
    default the adaptive ones of ``canny_thresholds``."""
    low, high = canny_thresholds(cv2.magnitude(dx, dy), params) if thresholds is None else thresholds
    dx16, dy16 = scaled_int16(dx, dy, _DERIVATIVE_SCALE)
    return cv2.Canny(dx16, dy16, low * _DERIVATIVE_SCALE, high * _DERIVATIVE_SCALE, L2gradient=True)


def hough_segments(edges: np.ndarray, params: EdgeParams) -> np.ndarray:
    """Raw (N, 2, 2) segments of a Canny edge map by probabilistic Hough, before merging."""
    min_length = params.raw_min_length_fraction * float(np.hypot(*edges.shape))
    lines = cv2.HoughLinesP(
        edges,
        rho=params.hough_rho,
        theta=np.deg2rad(params.hough_theta_deg),
        threshold=max(1, round(params.hough_vote_ratio * min_length)),
        minLineLength=min_length,
        maxLineGap=params.hough_max_gap,
    )
    if lines is None:
        return np.zeros((0, 2, 2))
    return lines.reshape(-1, 2, 2).astype(np.float64)


def lsd_segments(gray: np.ndarray, params: EdgeParams) -> np.ndarray:
    """Raw (N, 2, 2) segments of OpenCV's LSD, which fits its own gradient (no Canny).

    LSD returns many pieces of a few pixels, whose direction is meaningless; they are
    dropped here like HoughLinesP drops them (``raw_min_length_fraction``).
    """
    if params.blur_size > 1:
        gray = cv2.GaussianBlur(gray, (params.blur_size, params.blur_size), params.blur_sigma)
    image = np.clip(np.round(gray), 0, 255).astype(np.uint8)
    lines = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD).detect(image)[0]
    if lines is None:
        return np.zeros((0, 2, 2))
    lines = lines.reshape(-1, 2, 2).astype(np.float64)
    lengths = np.linalg.norm(lines[:, 1] - lines[:, 0], axis=1)
    return lines[lengths >= params.raw_min_length_fraction * float(np.hypot(*gray.shape))]


def merge_segments(segments: np.ndarray, params: EdgeParams) -> np.ndarray:
    """One segment per straight edge out of its broken and duplicated pieces, longest first.

    Nearest-neighbour clustering under the paper's two rules: a piece joins an edge if it
    is nearly parallel to it (``merge_angle_deg``, widened by 1 pixel over the piece's
    length because a short piece's direction is that uncertain), lies on it (both end
    points within ``merge_distance``: continuity) and overlaps it or is chained to it along
    the line through gaps up to ``merge_gap`` (contiguity).

    Pairs of pieces passing these tests on the longer one's line are found at once
    (angle-sorted windows, numpy) and linked into groups. A group whose pieces all pass
    the tests against the group's fitted line is one edge (all such groups at once). In
    any other group the longest free piece seeds an edge that absorbs the pieces
    compatible with its fitted line, refitting as it grows: chaining pairs alone would
    collapse a run of slightly turning pieces (a curved edge) into one long chord. The
    merged segment spans the projections of its pieces' end points onto the line. A seed's
    line, extrapolated from one piece, can strand distant pieces of its edge, so the result
    is merged again until nothing changes.
    """
    merged = _merge_once(segments, params)
    while len(merged) > 1:
        again = _merge_once(merged, params)
        if len(again) == len(merged):
            break
        merged = again
    return merged


def _merge_once(segments: np.ndarray, params: EdgeParams) -> np.ndarray:
    """One clustering pass of :func:`merge_segments`."""
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2)
    lengths = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)
    segments, lengths = segments[lengths > 0], lengths[lengths > 0]
    if len(segments) == 0:
        return np.zeros((0, 2, 2))
    unit = (segments[:, 1] - segments[:, 0]) / lengths[:, None]
    tolerance = np.minimum(np.deg2rad(params.merge_angle_deg) + np.arctan(1.0 / lengths), np.pi / 2)
    sin_tolerance = np.sin(tolerance)

    i, j = _candidate_pairs(np.arctan2(unit[:, 1], unit[:, 0]) % np.pi, tolerance + tolerance.max())
    longer = np.where(lengths[i] >= lengths[j], i, j)
    shorter = i + j - longer
    # cheap necessary test first: parallel pieces mostly lie on other lines
    offset = segments[shorter].mean(axis=1) - segments[longer, 0]
    near = np.abs(offset[:, 0] * unit[longer, 1] - offset[:, 1] * unit[longer, 0]) <= params.merge_distance
    i, j, longer, shorter = i[near], j[near], longer[near], shorter[near]
    joins = _joins(segments[shorter], unit[shorter], sin_tolerance[shorter],
                   segments[longer, 0], unit[longer], 0.0, lengths[longer], params)
    groups, label = connected_labels(len(segments), i[joins], j[joins])

    # the usual group is one straight edge: every piece fits the group's line, no growing needed
    centre, axis = _fit_lines(label, groups, segments.mean(axis=1), lengths, unit)
    normal = np.stack([-axis[:, 1], axis[:, 0]], axis=1)[label]
    offsets = segments - centre[label][:, None]
    fits = (np.abs((offsets * normal[:, None]).sum(axis=-1)).max(axis=1) <= params.merge_distance) & (
        np.abs((unit * normal).sum(axis=1)) <= sin_tolerance)
    straight = np.bincount(label, ~fits, minlength=groups) == 0
    lo, hi = _spans(label, groups, (offsets * axis[label][:, None]).sum(axis=-1))
    merged = [np.stack([centre + lo[:, None] * axis, centre + hi[:, None] * axis], axis=1)[straight]]

    curved = np.flatnonzero(~straight[label])
    curved = curved[np.lexsort((-lengths[curved], label[curved]))]  # by group, longest first
    for group in np.split(curved, np.flatnonzero(np.diff(label[curved])) + 1):
        if len(group):
            merged.append(_grow_edges(segments, unit, lengths, sin_tolerance, group, params))
    merged = np.concatenate(merged)
    return merged[np.argsort(-np.linalg.norm(merged[:, 1] - merged[:, 0], axis=1), kind="stable")]


def _spans(label: np.ndarray, groups: int, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per group, the lowest and highest of its pieces' end point positions ``t`` (K, 2) along
    its line (piece k in group label[k])."""
    lo, hi = np.full(groups, np.inf), np.full(groups, -np.inf)
    np.minimum.at(lo, label, t.min(axis=1))
    np.maximum.at(hi, label, t.max(axis=1))
    return lo, hi


def _candidate_pairs(angle: np.ndarray, window: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j), i != j, whose directions in [0, pi) differ (mod pi) by at most window[i].

    Only j at or after i in direction order is looked at, so ``window`` must bound the
    pair's tolerance from either side (tolerance[i] + max tolerance does).
    """
    n = len(angle)
    order = np.argsort(angle)
    sorted_angle, sorted_window = angle[order], window[order]
    wraps = sorted_angle < sorted_window.max()  # also compared with the directions just below pi
    extended_angle = np.concatenate([sorted_angle, sorted_angle[wraps] + np.pi])
    extended_index = np.concatenate([order, order[wraps]])
    reach = np.searchsorted(extended_angle, sorted_angle + sorted_window, side="right")
    counts = np.minimum(reach, np.arange(n) + n) - np.arange(n) - 1  # never back round to i
    first = np.repeat(np.arange(n), counts)
    second = first + 1 + np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    i, j = order[first], extended_index[second]
    return i[i != j], j[i != j]


def _joins(pieces, units, sin_tolerance, origin, axis, lo, hi, params: EdgeParams, chained=False) -> np.ndarray:
    """Which pieces (K, 2, 2) belong to the line(s) origin + t axis spanning t in [lo, hi].

    ``origin``/``axis`` are (2,) for one line or (K, 2) for one line per piece. With
    ``chained`` (one line) a piece may also be reached through other joining pieces.
    """
    normal = np.stack([-axis[..., 1], axis[..., 0]], axis=-1)
    offsets = pieces - origin[..., None, :]
    t = (offsets * axis[..., None, :]).sum(axis=-1)
    distance = np.abs((offsets * normal[..., None, :]).sum(axis=-1)).max(axis=-1)
    on_line = (np.abs((units * normal).sum(axis=-1)) <= sin_tolerance) & (distance <= params.merge_distance)
    if chained:
        on_line[on_line] = _chained(t[on_line].min(axis=-1), t[on_line].max(axis=-1), lo, hi, params.merge_gap)
        return on_line
    return on_line & (np.maximum(t.min(axis=-1) - hi, lo - t.max(axis=-1)) <= params.merge_gap)


def _grow_edges(segments, unit, lengths, sin_tolerance, group: np.ndarray, params: EdgeParams) -> np.ndarray:
    """Merged segments (M, 2, 2) of one group of linked pieces, ``group`` sorted longest first."""
    merged = []
    free = group
    while len(free):
        members, free = free[:1], free[1:]
        centre, axis = segments[members[0]].mean(axis=0), unit[members[0]]
        while len(free):
            t = (segments[members] - centre) @ axis
            joins = _joins(segments[free], unit[free], sin_tolerance[free], centre, axis, t.min(), t.max(), params,
                           chained=True)
            if not joins.any():
                break
            members, free = np.concatenate([members, free[joins]]), free[~joins]
            centre, axis = _fit_lines(np.zeros(len(members), dtype=int), 1, segments[members].mean(axis=1),
                                      lengths[members], unit[members])
            centre, axis = centre[0], axis[0]
        t = (segments[members] - centre) @ axis
        merged.append([centre + t.min() * axis, centre + t.max() * axis])
    return np.asarray(merged)


def _chained(lo: np.ndarray, hi: np.ndarray, start: float, end: float, gap: float) -> np.ndarray:
    """Which intervals [lo, hi] connect to [start, end], directly or through each other, with gaps <= gap."""
    all_lo, all_hi = np.concatenate([[start], lo]), np.concatenate([[end], hi])
    order = np.argsort(all_lo, kind="stable")
    reach = np.maximum.accumulate(all_hi[order])
    chain = np.empty(len(order), dtype=int)
    chain[order] = np.concatenate([[0], np.cumsum(all_lo[order][1:] > reach[:-1] + gap)])
    return chain[1:] == chain[0]


def refine_segments(segments: np.ndarray, edges: np.ndarray, params: EdgeParams) -> np.ndarray:
    """Segments refitted to the Canny pixels along them and extended over contiguous ones.

    Hough end points are single quantised pixels, and under noise HoughLinesP often loses
    the ends of an edge, especially near corners where blur bends the edge away from its
    line. The edge pixels within ``merge_distance`` of a segment's line are collected, the
    segment is extended over those that continue it in steps up to ``hough_max_gap``, and a
    least-squares line through the pixels of the extended span gives the result. Pixels are
    looked for up to ``merge_gap`` beyond each end; segments that grew nearly that far look
    again from their new ends, twice as far each round. A segment with fewer than two pixels
    is kept as it is. Pieces of one edge may overlap afterwards: run :func:`merge_segments`
    again.
    """
    refined = np.array(segments, dtype=np.float64).reshape(-1, 2, 2)
    active = np.flatnonzero(np.linalg.norm(refined[:, 1] - refined[:, 0], axis=1) > 0)
    window = max(params.merge_gap, 2.0 * params.hough_max_gap, 1.0)
    while len(active) and window < 2.0 * np.hypot(*edges.shape):
        before = refined[active]
        refined[active] = _refine_once(before, edges, params, window)
        length = np.linalg.norm(before[:, 1] - before[:, 0], axis=1)
        axis = (before[:, 1] - before[:, 0]) / length[:, None]
        t = ((refined[active] - before[:, :1]) * axis[:, None]).sum(axis=-1)
        reach = window - params.hough_max_gap  # grown this far: more pixels may follow
        active = active[(t[:, 0] < -reach) | (t[:, 1] > length + reach)]
        window *= 2.0
    return refined


def _refine_once(segments: np.ndarray, edges: np.ndarray, params: EdgeParams, window: float) -> np.ndarray:
    """One round of :func:`refine_segments`, looking ``window`` beyond the ends of segments of non-zero length."""
    count, centre, scatter, ends = edge_runs_kernel(segments, edges, float(params.merge_distance), float(window),
                                                    float(params.hough_max_gap))
    angle = 0.5 * np.arctan2(2.0 * scatter[:, 1], scatter[:, 0] - scatter[:, 2])  # as _fit_lines
    axis = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    fitted = np.flatnonzero(count >= 2)
    refined = segments.copy()
    for end in (0, 1):
        along = ((ends[fitted, end] - centre[fitted]) * axis[fitted]).sum(axis=1)
        refined[fitted, end] = centre[fitted] + along[:, None] * axis[fitted]
    return refined


def _fit_lines(label: np.ndarray, groups: int, midpoints: np.ndarray, lengths: np.ndarray,
               directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (groups, 2) and unit direction (groups, 2) of the least-squares line of each group.

    Segment k, of midpoint ``midpoints[k]``, length ``lengths[k]`` and unit direction
    ``directions[k]``, belongs to group label[k]; every point of it counts: that adds
    l^3 / 12 u u^T to the scatter matrix, so long pieces dominate and short noisy ones barely
    tilt the line. (``kernels.edge_runs_kernel`` fits the refinement's pixels.)
    """
    total = np.bincount(label, lengths, minlength=groups)
    with np.errstate(invalid="ignore", divide="ignore"):  # a group without items gets NaN
        centre = np.stack([np.bincount(label, lengths * midpoints[:, k], minlength=groups) for k in (0, 1)], axis=1)
        centre /= total[:, None]
    d = midpoints - centre[label]
    spread = lengths**3 / 12.0
    xx = lengths * d[:, 0] ** 2 + spread * directions[:, 0] ** 2
    xy = lengths * d[:, 0] * d[:, 1] + spread * directions[:, 0] * directions[:, 1]
    yy = lengths * d[:, 1] ** 2 + spread * directions[:, 1] ** 2
    xx, xy, yy = (np.bincount(label, m, minlength=groups) for m in (xx, xy, yy))
    angle = 0.5 * np.arctan2(2.0 * xy, xx - yy)  # principal axis of the scatter matrix
    return centre, np.stack([np.cos(angle), np.sin(angle)], axis=1)

"""Image edge stage against exact ground truth: polygons drawn with cv2, then blurred and noised."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from brepose_ros.image_codec import decode_image
from brepose_ros.online.image_edges import (EdgeParams, _refine_once, canny_edges, canny_thresholds, extract_segments,
                                            gradients, merge_segments, to_gray)
from brepose_ros.online.kernels import connected_labels, median_of_every_other, scaled_int16

BACKGROUND = 110.0
SIZE = (480, 640)


def rectangle(cx, cy, w, h, deg):
    return cv2.boxPoints(((cx, cy), (w, h), deg)).astype(np.float64)


def hexagon(cx, cy, radius, deg):
    angle = np.deg2rad(deg + 60.0 * np.arange(6))
    return np.stack([cx + radius * np.cos(angle), cy + radius * np.sin(angle)], axis=1)


SCENE = [rectangle(170, 150, 220, 120, 17), hexagon(460, 300, 110, 10), rectangle(200, 360, 160, 90, -35)]
GREYS = [170.0, 60.0, 145.0]


def draw(polygons, greys, noise=4.0, seed=0, size=SIZE):
    """uint8 image of filled polygons (sub-pixel vertices) on the background, blurred, noised."""
    image = np.full(size, BACKGROUND, np.float32)
    for polygon, grey in zip(polygons, greys):
        mask = np.zeros(size, np.uint8)
        cv2.fillPoly(mask, [np.round(polygon * 16).astype(np.int32)], 255, shift=4)
        image[mask > 0] = grey
    image = cv2.GaussianBlur(image, (0, 0), 1.0)
    image += np.random.default_rng(seed).normal(0.0, noise, size).astype(np.float32)
    return np.clip(np.round(image), 0, 255).astype(np.uint8)


def true_edges(polygons):
    return [np.array([p[i], p[(i + 1) % len(p)]]) for p in polygons for i in range(len(p))]


def along(edge, segments, distance=3.0, degrees=3.0):
    """Segments lying on the edge's line (both ends within distance) and overlapping it."""
    a, b = edge
    length = np.linalg.norm(b - a)
    u = (b - a) / length
    n = np.array([-u[1], u[0]])
    d = segments[:, 1] - segments[:, 0]
    cos = np.abs(d @ u) / np.linalg.norm(d, axis=1)
    t = (segments - a) @ u
    on_line = (np.abs((segments - a) @ n).max(axis=1) <= distance) & (cos >= np.cos(np.deg2rad(degrees)))
    return segments[on_line & (t.max(axis=1) > 0) & (t.min(axis=1) < length)]


def assert_recovered(edge, segments, end_tolerance=3.0, angle_tolerance=1.0):
    """Exactly one segment covers the edge, with both end points and its angle accurate."""
    found = along(edge, segments)
    assert len(found) == 1, f"edge {edge.tolist()}: {len(found)} segments along it: {found.tolist()}"
    s = found[0]
    ends = min(max(np.linalg.norm(s[0] - edge[0]), np.linalg.norm(s[1] - edge[1])),
               max(np.linalg.norm(s[0] - edge[1]), np.linalg.norm(s[1] - edge[0])))
    assert ends <= end_tolerance, f"edge {edge.tolist()}: end points off by {ends:.2f} px: {s.tolist()}"
    d, e = s[1] - s[0], edge[1] - edge[0]
    angle = np.degrees(np.arccos(min(1.0, abs(d @ e) / np.linalg.norm(d) / np.linalg.norm(e))))
    assert angle <= angle_tolerance, f"edge {edge.tolist()}: angle off by {angle:.2f} deg"


@pytest.mark.parametrize("detector, seed", [("hough", 0), ("hough", 1), ("lsd", 0)])
def test_every_polygon_edge_is_one_accurate_segment(detector, seed):
    segments = extract_segments(draw(SCENE, GREYS, seed=seed), EdgeParams(detector=detector))
    assert segments.dtype == np.float64 and segments.shape[1:] == (2, 2)
    for edge in true_edges(SCENE):
        assert_recovered(edge, segments)
    assert len(segments) == len(true_edges(SCENE)), "spurious segments"
    lengths = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)
    assert np.all(np.diff(lengths) <= 0), "not longest first"


def test_low_contrast_image_still_finds_every_edge():
    """A dim image (contrast 5-9 grey levels, noise 1) lowers the thresholds instead of losing edges."""
    dim_greys = [BACKGROUND + 0.15 * (g - BACKGROUND) for g in GREYS]
    dim = draw(SCENE, dim_greys, noise=1.0)
    segments = extract_segments(dim)
    for edge in true_edges(SCENE):
        assert_recovered(edge, segments)
    params = EdgeParams()
    bright_high = canny_thresholds(_gradient(draw(SCENE, GREYS, noise=4.0)), params)[1]
    dim_high = canny_thresholds(_gradient(dim), params)[1]
    assert dim_high < bright_high / 2
    assert np.count_nonzero(cv2.Canny(dim, 50, 150)) < 20, "a fixed threshold would have found these edges too"


def _gradient(image):
    return cv2.magnitude(*gradients(to_gray(image), EdgeParams()))


def test_broken_line_merges_into_one_segment():
    """Collinear blocks with 8 px gaps: their common top edge comes out whole."""
    angle = np.deg2rad(8.0)
    u, n = np.array([np.cos(angle), np.sin(angle)]), np.array([-np.sin(angle), np.cos(angle)])
    start = np.array([80.0, 200.0])
    blocks = [np.array([start + a * u, start + (a + 60) * u, start + (a + 60) * u + 50 * n, start + a * u + 50 * n])
              for a in range(0, 5 * 68, 68)]
    segments = extract_segments(draw(blocks, [175.0] * len(blocks)))
    top = np.array([start, start + (4 * 68 + 60) * u])
    assert_recovered(top, segments)


def test_vertical_and_horizontal_steps_land_between_their_pixels():
    """x right, y down, pixel centres at integers: a step between columns 99 and 100 is at x = 99.5."""
    image = np.full(SIZE, 60, np.uint8)
    image[:, 100:] = 180  # vertical step
    image[300:, :] = 20  # horizontal step
    segments = extract_segments(image)
    vertical = segments[np.abs(segments[:, 1, 0] - segments[:, 0, 0]) < 1]
    horizontal = segments[np.abs(segments[:, 1, 1] - segments[:, 0, 1]) < 1]
    assert len(vertical) == 1 and len(horizontal) == 1
    assert np.all(np.abs(vertical[0, :, 0] - 99.5) <= 0.6)
    assert np.all(np.abs(horizontal[0, :, 1] - 299.5) <= 0.6)
    assert sorted(vertical[0, :, 1]) == pytest.approx([0, 299], abs=3)
    assert sorted(horizontal[0, :, 0]) == pytest.approx([0, 639], abs=3)


def test_duplicates_and_broken_pieces_collapse_but_neighbours_stay():
    """Pieces of one line (gaps, 1 px offsets, jitter) become one; a parallel line 8 px off does not join."""
    rng = np.random.default_rng(3)
    u = np.array([np.cos(0.3), np.sin(0.3)])
    n = np.array([-u[1], u[0]])
    origin = np.array([100.0, 50.0])
    pieces = []
    for a, b in [(0, 80), (86, 150), (155, 240), (248, 300), (20, 130), (140, 290)]:  # broken + duplicates
        shift = rng.uniform(-0.8, 0.8, size=2)
        pieces.append([origin + a * u + shift[0] * n, origin + b * u + shift[1] * n])
    parallel = [[origin + 8 * n, origin + 300 * u + 8 * n]]
    beyond = [[origin + 340 * u, origin + 400 * u]]  # collinear, 40 px gap
    merged = merge_segments(np.array(pieces + parallel + beyond), EdgeParams())
    assert len(merged) == 3
    line = merged[0]
    ends = np.sort((line - origin) @ u)
    assert ends == pytest.approx([0, 300], abs=1.0)
    assert np.abs((line - origin) @ n).max() < 0.5


def test_curved_edge_is_not_collapsed_into_one_chord():
    """Short pieces along an arc turn little from piece to piece, but no merged segment leaves the arc."""
    radius, centre = 300.0, np.array([0.0, 0.0])
    angles = np.deg2rad(np.linspace(0, 90, 31))
    points = centre + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    merged = merge_segments(np.stack([points[:-1], points[1:]], axis=1), EdgeParams())
    assert len(merged) >= 4
    mid = merged.mean(axis=1)
    sagitta = radius - np.linalg.norm(mid - centre, axis=1)
    assert sagitta.max() <= 2 * EdgeParams().merge_distance


def test_merge_of_a_thousand_pieces_finds_every_line():
    """100 lines (10 directions x 10 offsets) cut into 11 jittered pieces each: 100 merged lines."""
    rng = np.random.default_rng(7)
    pieces = []
    for k in range(10):
        u = np.array([np.cos(np.deg2rad(18 * k)), np.sin(np.deg2rad(18 * k))])
        n = np.array([-u[1], u[0]])
        for offset in range(10):
            origin = np.array([320.0, 240.0]) + (offset - 4.5) * 40 * n - 200 * u
            cuts = np.linspace(0, 400, 12)[1:-1] + rng.uniform(-10, 10, 10)
            for a, b in zip(np.r_[0, cuts + 4], np.r_[cuts, 400]):  # 4 px gaps
                pieces.append([origin + a * u + rng.normal(0, 0.3) * n, origin + b * u + rng.normal(0, 0.3) * n])
    merged = merge_segments(np.array(pieces), EdgeParams())
    assert len(pieces) >= 1000
    assert len(merged) == 100
    assert np.linalg.norm(merged[:, 1] - merged[:, 0], axis=1) == pytest.approx(400, abs=2)


def test_merge_groups_pieces_as_scipys_connected_components_would():
    """kernels.connected_labels, the merge's grouping of joined pieces, numbers the
    components of random graphs (isolated nodes, repeated and self edges) as scipy does."""
    rng = np.random.default_rng(3)
    for _ in range(300):
        n = int(rng.integers(1, 60))
        first, second = rng.integers(0, n, size=(2, int(rng.integers(0, 2 * n))))
        graph = coo_matrix((np.ones(len(first)), (first, second)), shape=(n, n))
        count, labels = connected_labels(n, first, second)
        expected_count, expected = connected_components(graph, directed=False)
        assert count == expected_count
        assert np.array_equal(labels, expected)


def test_canny_inputs_compiled_are_numpys():
    """The compiled steps before Canny (kernels.median_of_every_other, kernels.scaled_int16)
    equal numpy's to the bit: gradient magnitudes of a noisy image and maps of odd and even
    sizes with many equal values, derivatives on exact halves (rounded to even)."""
    magnitude = _gradient(draw(SCENE, GREYS, noise=4.0))
    assert float(median_of_every_other(magnitude)) == float(np.median(magnitude[::2, ::2]))
    rng = np.random.default_rng(2)
    for shape in [(1, 1), (3, 5), (6, 4), (33, 17), (40, 40)]:
        values = np.round(np.abs(rng.normal(0, 8, shape)), 1).astype(np.float32)
        assert float(median_of_every_other(values)) == float(np.median(values[::2, ::2]))
        halves = (rng.integers(-4000, 4000, shape) / 32).astype(np.float32)
        for ours, numpys in zip(scaled_int16(halves, -halves, 16.0), (halves, -halves)):
            assert np.array_equal(ours, np.round(numpys * 16.0).astype(np.int16))


def _numpy_pixels_along(segments, edges, distance, window):
    """The numpy band walk that ``kernels.edge_runs_kernel`` replaced, kept as its reference."""
    first = segments[:, 0]
    unit = (segments[:, 1] - first) / np.linalg.norm(segments[:, 1] - first, axis=1)[:, None]
    steep = np.abs(unit[:, 1]) > np.abs(unit[:, 0])
    major_first, minor_first = np.where(steep, first[:, 1], first[:, 0]), np.where(steep, first[:, 0], first[:, 1])
    major_unit, minor_unit = np.where(steep, unit[:, 1], unit[:, 0]), np.where(steep, unit[:, 0], unit[:, 1])
    height, width = edges.shape
    reach = np.linalg.norm(segments[:, 1] - first, axis=1) + window
    ends = major_first[:, None] + np.stack([np.full_like(reach, -window), reach], axis=1) * major_unit[:, None]
    lo = np.maximum(np.ceil(ends.min(axis=1)), 0).astype(np.intp)
    hi = np.minimum(np.floor(ends.max(axis=1)), np.where(steep, height, width) - 1).astype(np.intp)
    counts = np.maximum(hi - lo + 1, 0)
    owner = np.repeat(np.arange(len(segments)), counts)
    major = lo[owner] + np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    minor_centre = minor_first[owner] + (major - major_first[owner]) * minor_unit[owner] / major_unit[owner]
    half = int(distance * np.sqrt(2) + 0.5)
    minor = np.round(minor_centre).astype(np.intp)[:, None] + np.arange(-half, half + 1)
    sample_steep = steep[owner][:, None]
    hit = (minor >= 0) & (minor < np.where(sample_steep, width, height))
    flat = np.where(sample_steep, major[:, None] * width + minor, minor * width + major[:, None])
    hit[hit] = edges.ravel()[flat[hit]] > 0
    rows, columns = np.nonzero(hit)
    owner, flat = owner[rows], flat[rows, columns]
    pixels = np.stack([flat % width, flat // width], axis=1).astype(np.float64)
    offsets = pixels - first[owner]
    t = (offsets * unit[owner]).sum(axis=1)
    near = np.abs(offsets[:, 0] * unit[owner, 1] - offsets[:, 1] * unit[owner, 0]) <= distance
    return owner[near], pixels[near], t[near]


def _numpy_refine_once(segments, edges, params, window):
    """``image_edges._refine_once`` as numpy computed it before ``kernels.edge_runs_kernel``."""
    n = len(segments)
    lengths = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)
    owner, pixels, t = _numpy_pixels_along(segments, edges, params.merge_distance, window)
    owner = np.concatenate([owner, np.arange(n), np.arange(n)])
    t = np.concatenate([t, np.zeros(n), lengths])
    virtual = np.arange(len(owner)) >= len(pixels)
    order = np.lexsort((t, owner))
    owner, t, virtual = owner[order], t[order], virtual[order]
    pixels = np.concatenate([pixels, np.zeros((2 * n, 2))])[order]
    inside = (t >= 0) & (t <= lengths[owner])
    breaks = (np.diff(owner) != 0) | ((np.diff(t) > params.hough_max_gap) & ~(inside[:-1] & inside[1:]))
    run = np.concatenate([[0], np.cumsum(breaks)])
    core = np.zeros(n, dtype=int)
    core[owner[virtual]] = run[virtual]
    keep = ~virtual & (run == core[owner])
    owner, pixels = owner[keep], pixels[keep]
    fitted = np.flatnonzero(np.bincount(owner, minlength=n) >= 2)
    weight = np.ones(len(owner))  # the least-squares line through each segment's pixels
    with np.errstate(invalid="ignore", divide="ignore"):
        centre = np.stack([np.bincount(owner, weight * pixels[:, k], minlength=n) for k in (0, 1)], axis=1)
        centre /= np.bincount(owner, weight, minlength=n)[:, None]
    d = pixels - centre[owner]
    xx, xy, yy = (np.bincount(owner, m, minlength=n)
                  for m in (weight * d[:, 0] ** 2, weight * d[:, 0] * d[:, 1], weight * d[:, 1] ** 2))
    angle = 0.5 * np.arctan2(2.0 * xy, xx - yy)
    axis = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    first = np.searchsorted(owner, fitted)
    last = np.searchsorted(owner, fitted, side="right") - 1
    refined = segments.copy()
    for end, index in ((0, first), (1, last)):
        along = ((pixels[index] - centre[fitted]) * axis[fitted]).sum(axis=1)
        refined[fitted, end] = centre[fitted] + along[:, None] * axis[fitted]
    return refined


def test_refinement_compiled_is_numpys():
    """A refinement round (``_refine_once``, its pixel walk and fit compiled in
    ``kernels.edge_runs_kernel``) gives numpy's segments to the bit: random edge maps of
    lines and scattered pixels, random segments of every direction, most drawn on the map,
    some partly outside the image, with pixel-centred and half-pixel ends (exact roundings), at several windows."""
    rng = np.random.default_rng(11)
    params = EdgeParams()
    for trial in range(60):
        height, width = int(rng.integers(20, 200)), int(rng.integers(20, 200))
        edges = np.where(rng.random((height, width)) < rng.uniform(0.0, 0.08), 255, 0).astype(np.uint8)
        for _ in range(int(rng.integers(0, 8))):
            a, b = rng.uniform(-10, [width + 10, height + 10], (2, 2))
            cv2.line(edges, tuple(int(v) for v in a), tuple(int(v) for v in b), 255, 1)
        n = int(rng.integers(1, 25))
        segments = rng.uniform(-15, [width + 15, height + 15], (n, 2, 2))
        if trial % 3 == 0:
            segments = np.round(segments * 2) / 2  # ends on pixels and half pixels
        segments[0] = np.clip(segments[0], 0, [width - 1, height - 1])
        segments = segments[np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1) > 0]
        for a, b in segments[: int(rng.integers(1, n + 1))]:  # as Hough's, most on edge pixels
            cv2.line(edges, tuple(int(v) for v in np.round(a)), tuple(int(v) for v in np.round(b)), 255, 1)
        for window in (1.0, 7.0, 40.0):
            ours = _refine_once(segments, edges, params, window)
            assert ours.tobytes() == _numpy_refine_once(segments, edges, params, window).tobytes()


@pytest.mark.parametrize("noise", [4.0, 12.0])
def test_noisy_blank_image_gives_few_segments(noise):
    image = np.clip(np.random.default_rng(0).normal(120, noise, SIZE), 0, 255).astype(np.uint8)
    assert len(extract_segments(image)) <= 2
    assert np.count_nonzero(canny_edges(to_gray(image), EdgeParams())) < 500


@pytest.mark.parametrize("image", [
    np.full(SIZE, 77, np.uint8),
    np.full(SIZE + (3,), 4000, np.uint16),
    np.full((5, 7, 4), 255, np.uint8),
    np.zeros((1, 1), np.float32),
])
def test_constant_image_gives_no_segments(image):
    segments = extract_segments(image)
    assert segments.shape == (0, 2, 2) and segments.dtype == np.float64


def test_gray_colour_and_depth_variants_agree():
    gray = draw(SCENE, GREYS)
    expected = extract_segments(gray)
    variants = [gray[:, :, None], cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR), cv2.cvtColor(gray, cv2.COLOR_GRAY2BGRA),
                gray.astype(np.uint16) * 257, gray.astype(np.float32)]
    for image in variants:
        np.testing.assert_allclose(extract_segments(image), expected, atol=1e-6)


def hue_scene(seed: int = 0) -> np.ndarray:
    """BGR polygons of the background's brightness but another hue (BGR 110, 64, 200 on grey
    110: 0.1 grey levels apart), each channel noised on its own."""
    hue = [(110.0, 64.0, 200.0)] * len(SCENE)
    return np.stack([draw(SCENE, [c[k] for c in hue], noise=2.0, seed=seed + k) for k in range(3)], axis=2)


def test_colour_edges_find_a_hue_edge_the_grey_image_averages_away():
    """Regions of one luminance and two hues: edges.colour finds every boundary in the
    opponent-colour planes, the grey image none; a grey picture stored as BGR gives the same
    segments either way."""
    image = hue_scene()
    assert abs(float(to_gray(image).mean()) - BACKGROUND) < 1.0
    colour = extract_segments(image, EdgeParams(colour=True))
    for edge in true_edges(SCENE):
        assert_recovered(edge, colour)
    assert not any(len(along(edge, extract_segments(image, EdgeParams(colour=False)))) for edge in true_edges(SCENE))
    grey = cv2.cvtColor(draw(SCENE, GREYS), cv2.COLOR_GRAY2BGR)
    np.testing.assert_array_equal(extract_segments(grey, EdgeParams(colour=True)), extract_segments(grey))


def test_colour_edges_keep_the_faint_luminance_edges_of_the_grey_image():
    """Grey polygons 7-12 levels off the background under noise of 3 levels in each channel
    on its own: the grey image (the channels' mean, less noisy) finds every edge, and so do
    the colour edges, whose luminance plane keeps the grey threshold (the strongest raw
    B, G or R gradient, noisier, raised it and found 10 of 14: docs/results/real_lmo.md)."""
    faint = [BACKGROUND + 0.2 * (g - BACKGROUND) for g in GREYS]
    image = np.stack([draw(SCENE, faint, noise=3.0, seed=k) for k in range(3)], axis=2)
    for params in (EdgeParams(colour=False), EdgeParams(colour=True)):
        segments = extract_segments(image, params)
        for edge in true_edges(SCENE):
            assert_recovered(edge, segments)


def test_a_colour_frame_as_the_node_receives_it_keeps_its_hue_edges():
    """An rgb8 sensor_msgs/Image's fields, decoded as the node does (image_codec), reach the
    edge stage in colour: the default parameters find the hue boundaries."""
    bgr = hue_scene(seed=3)
    rgb = np.ascontiguousarray(bgr[:, :, ::-1])
    decoded = decode_image("rgb8", rgb.shape[0], rgb.shape[1], rgb.shape[1] * 3, rgb.tobytes())
    np.testing.assert_array_equal(decoded, bgr)
    segments = extract_segments(decoded)
    for edge in true_edges(SCENE):
        assert_recovered(edge, segments)


@pytest.mark.parametrize("image, message", [
    (np.zeros((0, 0), np.uint8), "empty"),
    (np.zeros((0, 5, 3), np.uint8), "empty"),
    (np.zeros(10, np.uint8), "shape"),
    (np.zeros((4, 4, 3, 1), np.uint8), "shape"),
    (np.zeros((4, 4, 2), np.uint8), "channels"),
    (np.zeros((4, 4), np.int32), "dtype"),
    (np.zeros((4, 4), bool), "dtype"),
    (np.array([[0.0, np.nan], [1.0, 2.0]]), "NaN"),
    (np.array([[0.0, np.inf], [1.0, 2.0]], np.float32), "NaN or infinite"),
])
def test_bad_images_raise_value_error(image, message):
    with pytest.raises(ValueError, match=message):
        extract_segments(image)


@pytest.mark.parametrize("changes", [
    {"detector": "canny"}, {"blur_size": 4}, {"canny_low_ratio": 1.5}, {"merge_gap": -1.0}, {"max_segments": 0},
])
def test_bad_params_raise_value_error(changes):
    with pytest.raises(ValueError):
        EdgeParams(**changes)


def test_max_segments_keeps_the_longest():
    everything = extract_segments(draw(SCENE, GREYS))
    five = extract_segments(draw(SCENE, GREYS), EdgeParams(max_segments=5))
    np.testing.assert_allclose(five, everything[:5])

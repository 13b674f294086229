"""The template search (online/search.py): its a-contrario score on drawn scenes with a
known answer, and the estimator with the search as its generator on rendered scenes."""
import cv2
import numpy as np
import pytest

from brepose_ros.online import search
from brepose_ros.online.scoring import EdgeEvidence
from brepose_ros.params import SearchParams


def bracket_outline(size: float) -> np.ndarray:
    """An L-shaped plate with a window, segments (N, 2, 2) about its centre, unit ``size``."""
    outer = np.array([[0, 0], [1, 0], [1, 0.35], [0.35, 0.35], [0.35, 1], [0, 1]]) - 0.4
    window = np.array([[0.1, 0.1], [0.25, 0.1], [0.25, 0.25], [0.1, 0.25]]) - 0.4
    segs = [np.stack([poly, np.roll(poly, -1, axis=0)], axis=1) for poly in (outer, window)]
    return np.concatenate(segs) * size


def draw(edge_map: np.ndarray, segments: np.ndarray) -> None:
    for (x0, y0), (x1, y1) in np.rint(segments).astype(int):
        cv2.line(edge_map, (int(x0), int(y0)), (int(x1), int(y1)), 255, 1)


def evidence_of(edge_map: np.ndarray) -> EdgeEvidence:
    """Edge evidence whose directions come from the drawn lines (a blurred gradient)."""
    blurred = cv2.GaussianBlur(edge_map.astype(np.float32), (7, 7), 0)
    gx, gy = cv2.Sobel(blurred, cv2.CV_32F, 1, 0), cv2.Sobel(blurred, cv2.CV_32F, 0, 1)
    # a drawn line's gradient points across it on both sides: its direction is right modulo pi
    return EdgeEvidence(edge_map, gx, gy)


def template_scores(evidence, points, angles, candidates, factor=4, spread=1):
    """Each candidate (dx_px, dy_px, turn, scale) scored at the position it names: the kernel's
    best position restricted to that one cell by a map of chance evaluated there."""
    sizes = np.array([220.0])
    pad = 80
    maps = search.ResponseMaps.of(evidence, factor, spread, pad)
    chance = maps.chance(int(sizes[0] / factor) | 1)[None]
    out = []
    for shift_x, shift_y, turn, scale in candidates:
        c, s = np.cos(turn), np.sin(turn)
        pts = points @ np.array([[c, s], [-s, c]]) * scale
        dx = np.rint(pts[:, 0] / factor).astype(np.int16)[None]
        dy = np.rint(pts[:, 1] / factor).astype(np.int16)[None]
        bins = (np.mod(angles + turn, np.pi) / np.pi * search.BINS).astype(np.uint8)[None] % search.BINS
        score, y, x = np.zeros(1), np.zeros(1, np.int64), np.zeros(1, np.int64)
        search.score_templates(maps.maps, pad, dx, dy, bins, np.zeros(1, np.int64), chance, len(points) // 4, 0.0,
                               score, y, x)
        out.append((score[0], x[0] * factor + (factor - 1) / 2 - shift_x, y[0] * factor + (factor - 1) / 2 - shift_y))
    return out


def test_occluded_part_among_clutter_ranks_first_and_is_placed_right():
    """A bracket 40 % hidden behind a bar, beside clutter (a grid of lines and a second,
    smaller copy turned 90 degrees): the true template outscores every turned (15-180
    degrees) and rescaled (0.7-1.4) one, and its best position is the part's centre
    within the coarse grid's spread."""
    rng = np.random.default_rng(0)
    h, w, center = 480, 640, np.array([250.0, 240.0])
    edge_map = np.zeros((h, w), np.uint8)
    part = bracket_outline(200.0)
    draw(edge_map, part + center)
    edge_map[:, 250:340] = 0  # the occluder hides a vertical band...
    draw(edge_map, np.array([[[250, 0], [250, 479]], [[340, 0], [340, 479]]], float))  # ...and shows its sides
    for x in range(420, 640, 18):  # clutter: dense parallel lines, then a turned copy
        draw(edge_map, np.array([[[x, 20], [x, 200]]], float))
    turned = bracket_outline(120.0) @ np.array([[0.0, 1.0], [-1.0, 0.0]])
    draw(edge_map, turned + [520, 360])
    draw(edge_map, rng.uniform(0, [w, h], size=(12, 2, 2)))
    evidence = evidence_of(edge_map)
    points, angles = search.template_points(part, 48)
    candidates = [(0, 0, 0.0, 1.0)] + [(0, 0, np.radians(a), 1.0) for a in (15, 30, 90, 180, 270)] \
        + [(0, 0, 0.0, k) for k in (0.7, 0.8, 1.25, 1.4)]
    scored = template_scores(evidence, points, angles, candidates)
    true_score, x, y = scored[0]
    assert true_score > max(s for s, _, _ in scored[1:]) + 0.05, [round(s, 2) for s, _, _ in scored]
    assert np.hypot(x - center[0], y - center[1]) <= 2 * 4, (x, y)  # two coarse cells: the spread


def test_an_edge_on_template_scores_low_on_a_straight_edge():
    """Points all of one direction (a view seen edge-on) along a long straight image edge hit
    every time, but so would any points there: the a-contrario score stays low."""
    edge_map = np.zeros((240, 320), np.uint8)
    for y in range(40, 200, 10):
        draw(edge_map, np.array([[[20, y], [300, y]]], float))
    evidence = evidence_of(edge_map)
    line = np.array([[[-60.0, 0.0], [60.0, 0.0]], [[-60.0, 3.0], [60.0, 3.0]]])
    points, angles = search.template_points(line, 32)
    (score, _, _), = template_scores(evidence, points, angles, [(0, 0, 0.0, 1.0)])
    assert score < 0.35, score


def test_template_points_lie_on_the_segments_evenly_by_length():
    segments = np.array([[[0.0, 0.0], [3.0, 0.0]], [[3.0, 0.0], [3.0, 1.0]]])
    points, angles = search.template_points(segments, 8)
    order = np.lexsort((points[:, 1], points[:, 0]))  # the probes come first; sort back by x, then y
    points, angles = points[order], angles[order]
    assert np.allclose(points[:6, 1], 0.0) and np.allclose(points[6:, 0], 3.0)
    assert np.allclose(angles[:6], 0.0) and np.allclose(angles[6:], np.pi / 2)


def test_search_params_refuse_an_unknown_generator_and_an_empty_size_range():
    with pytest.raises(ValueError, match="generators"):
        SearchParams(generators="lines")
    with pytest.raises(ValueError, match="max_size_fraction"):
        SearchParams(min_size_fraction=0.5, max_size_fraction=0.4)

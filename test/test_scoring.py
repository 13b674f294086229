"""Edge evidence (the score's two shares and the polish's pairing) against plain reference
versions and on images with known answers."""
import cv2
import numpy as np
import pytest

from brepose_ros.online import scoring
from brepose_ros.online.image_edges import EdgeParams, canny_from_gradients, gradients
from brepose_ros.params import PoseParams

#: the score's margin floor by default (pose.min_margin_pixels)
MARGIN = PoseParams().min_margin_pixels


def random_segments(rng, n, scale=1.0):
    return rng.uniform(-1, 1, size=(n, 2, 2)) * scale


def square(center, side):
    corners = np.asarray(center, float) + side / 2 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


def test_a_pose_fitting_only_a_hole_does_not_explain_the_part_around_it():
    """A 60 px window inside a 100 px part: a pose drawing only the window explains its own
    edges, but the outline's margin of at least pose.min_margin_pixels (40) takes in the part's
    outer edges 20 px away, which it does not explain; the whole part's pose explains all. With
    a floor of 10 px the margin no longer reaches them."""
    outer, window = square((160, 120), 100), square((160, 120), 60)
    edge_map = np.zeros((240, 320), np.uint8)
    for (x0, y0), (x1, y1) in np.concatenate([outer, window]).astype(int):
        cv2.line(edge_map, (int(x0), int(y0)), (int(x1), int(y1)), 255, 1)
    flat = np.zeros(edge_map.shape, np.float32)
    evidence = scoring.EdgeEvidence(edge_map, flat, flat)
    assert evidence.explained(window, 2.0, MARGIN) < 0.5
    assert evidence.explained(window, 2.0, 10.0) == 1.0
    assert evidence.explained(np.concatenate([outer, window]), 2.0, MARGIN) == 1.0


def test_an_edge_pixel_pairs_with_a_model_point_only_if_it_runs_alike():
    """The polish's pairing (EdgeEvidence.nearest_edges): a point 2 px below a horizontal
    image edge finds it for a horizontal model edge, not for a vertical one."""
    gray = np.full((240, 320), 50, np.float32)
    gray[120:] = 200
    evidence = scoring.EdgeEvidence(*edge_stage(gray))
    point = np.array([[200.0, 121.0]])
    horizontal = evidence.orientation_bin(np.array([[[0.0, 0.0], [1.0, 0.0]]]))
    vertical = evidence.orientation_bin(np.array([[[0.0, 0.0], [0.0, 1.0]]]))
    edge, found = evidence.nearest_edges(point, horizontal, radius_px=2.0)
    assert found.tolist() == [True] and edge.tolist() == [[200.0, 119.0]]
    assert evidence.nearest_edges(point, vertical, radius_px=2.0)[1].tolist() == [False]


def edge_stage(gray):
    """Canny's edge map and the gradient it ran on, at the default edge parameters."""
    dx, dy = gradients(gray, EdgeParams())
    return canny_from_gradients(dx, dy, EdgeParams()), dx, dy


def test_chamfer_ball_dilation_is_the_thresholded_distance_transform():
    rng = np.random.default_rng(2)
    for radius in (0.0, 0.5, 1.0, 1.4, 2.0, 2.5, 3.0, 4.7, 9.0):
        edges = (rng.random((60, 80)) < 0.01).astype(np.uint8)
        dist = cv2.distanceTransform(np.where(edges > 0, 0, 255).astype(np.uint8), cv2.DIST_L2, 3)
        assert np.array_equal(cv2.dilate(edges, scoring.chamfer_ball(radius)) > 0, dist <= radius)


@pytest.fixture(scope="module")
def evidence_image():
    """A grey image with a few shapes, its Canny edges and projected model segments near them."""
    rng = np.random.default_rng(3)
    gray = np.full((240, 320), 40, np.uint8)
    cv2.rectangle(gray, (60, 50), (200, 170), 200, -1)
    cv2.circle(gray, (250, 120), 40, 120, -1)
    cv2.line(gray, (10, 220), (300, 190), 255, 3)
    edge_map = cv2.Canny(gray, 50, 150)
    corners = np.array([[60, 50], [200, 50], [200, 170], [60, 170]], float)
    square = np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
    models = [square + rng.normal(0, s, size=square.shape) for s in (0.0, 1.0, 2.5, 6.0)]
    models.append(np.concatenate([square, random_segments(rng, 6, 150) + [160, 120]]))
    models.append(square * 0.5 + [190, 90])  # small, over the circle
    models.append(square + [150, 20])  # partly outside the image
    return edge_map, gray, models


def evidence_of(edge_map, gray):
    """EdgeEvidence on the gradient of the edge stage's default blur."""
    return scoring.EdgeEvidence(edge_map, *gradients(gray.astype(np.float32), EdgeParams()))


def reference_support(edge_map, gray, model_px, tolerance):
    """EdgeEvidence.supports of one pose as first written: one distance map per direction bin, three look-ups."""
    ev = evidence_of(edge_map, gray)
    smooth = cv2.GaussianBlur(gray.astype(np.float32), (5, 5), 0)
    dx, dy = cv2.Sobel(smooth, cv2.CV_32F, 1, 0), cv2.Sobel(smooth, cv2.CV_32F, 0, 1)
    bins = (np.mod(np.arctan2(dy, dx) + np.pi / 2, np.pi) / np.pi * ev.BINS).astype(int) % ev.BINS
    maps = np.stack([cv2.distanceTransform(np.where((edge_map > 0) & (bins == b), 0, 255).astype(np.uint8),
                                           cv2.DIST_L2, 3) for b in range(ev.BINS)])
    h, w = edge_map.shape
    total = near = 0.0
    for seg, own in zip(model_px, ev.orientation_bin(model_px)):
        length = np.linalg.norm(seg[1] - seg[0])
        count = int(np.clip(np.ceil(length / 2.0), 1, 2000))
        for k in range(count):
            x, y = np.round(seg[0] + (k + 0.5) / count * (seg[1] - seg[0])).astype(int)
            total += length / count
            if 0 <= x < w and 0 <= y < h and min(maps[(own + s) % ev.BINS, y, x] for s in (-1, 0, 1)) <= tolerance:
                near += length / count
    return near / total


def reference_explained(edge_map, model_px, tolerance):
    """explained without the bounding-box crop: the whole image, a distance transform."""
    h, w = edge_map.shape
    pts = np.clip(model_px.reshape(-1, 2), -4.0 * max(h, w), 5.0 * max(h, w))
    hull = scoring.EdgeEvidence.grown_outline(pts, MARGIN)
    outline = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(outline, np.round(hull).astype(np.int32), 1)
    inside = (edge_map > 0) & (outline > 0)
    canvas = np.full((h, w), 255, np.uint8)
    for (x0, y0), (x1, y1) in np.round(pts.reshape(-1, 2, 2)).astype(int):
        cv2.line(canvas, (int(x0), int(y0)), (int(x1), int(y1)), 0, 1)
    near = cv2.distanceTransform(canvas, cv2.DIST_L2, 3) <= tolerance
    return (near & inside).sum() / max(inside.sum(), 1)


@pytest.mark.parametrize("tolerance", [1.0, 2.0, 3.5])
def test_edge_evidence_matches_the_distance_transform_definitions(evidence_image, tolerance):
    edge_map, gray, models = evidence_image
    evidence = evidence_of(edge_map, gray)
    for model_px in models:
        assert evidence.supports(model_px, np.array([0, len(model_px)]), tolerance)[0] == pytest.approx(
            reference_support(edge_map, gray, model_px, tolerance), abs=1e-12)
        assert evidence.explained(model_px, tolerance, MARGIN) == pytest.approx(
            reference_explained(edge_map, model_px, tolerance), abs=1e-12)


def test_supports_of_a_batch_are_each_pose_alone(evidence_image):
    edge_map, gray, models = evidence_image
    evidence = evidence_of(edge_map, gray)
    spans = np.cumsum([0] + [len(m) for m in models])
    together = evidence.supports(np.concatenate(models), spans, 2.0)
    assert [float(s) for s in together] == [float(evidence.supports(m, np.array([0, len(m)]), 2.0)[0])
                                            for m in models]

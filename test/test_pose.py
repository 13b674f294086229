"""Pose refinement, line association and edge evidence against plain reference versions:
the fast code paths must give the same answers as the straightforward definitions."""
import cv2
import numpy as np
import pytest

from brepose_ros.camera import project_normalised
from brepose_ros.geometry import rot_z, rotation_angle_deg
from brepose_ros.online import refinement, scoring
from brepose_ros.online.image_edges import EdgeParams, canny_from_gradients, gradients
from brepose_ros.online.lines2d import nearest_lines


def random_segments(rng, n, scale=1.0):
    return rng.uniform(-1, 1, size=(n, 2, 2)) * scale


def exact_line_matches(rng, n, R, t):
    """n model segments and the image lines they project onto under (R, t), lines longer
    than the projected edges: only the lines matter."""
    model_3d = rng.uniform(-0.05, 0.05, size=(n, 2, 3))
    image_2d = project_normalised(model_3d, R, t)
    return model_3d, image_2d + np.array([-0.3, 0.3])[None, :, None] * (image_2d[:, 1:] - image_2d[:, :1])


def test_refine_poses_recovers_each_pose_of_a_batch_from_exact_line_matches():
    rng = np.random.default_rng(0)
    R_true = [rot_z(0.4) @ cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))[0], cv2.Rodrigues(np.array([-1.0, 0.5, 0.2]))[0]]
    t_true = [np.array([0.01, -0.02, 0.5]), np.array([-0.05, 0.03, 0.8])]
    pairs = [exact_line_matches(rng, n, R, t) for n, R, t in zip((12, 9), R_true, t_true)]
    R0 = [cv2.Rodrigues(np.array([0.03, 0.02, -0.02]))[0] @ R for R in R_true]
    t0 = [t + [0.005, -0.003, 0.02] for t in t_true]
    # a third pose with only 2 pairs cannot be refined and stays where it is
    R0.append(np.eye(3)), t0.append(np.array([0.0, 0.0, 1.0]))
    pairs.append(exact_line_matches(rng, 2, np.eye(3), np.array([0.0, 0.0, 0.9])))
    spans = np.cumsum([0] + [len(m) for m, _ in pairs])
    R, t = refinement.refine_poses(np.array(R0), np.array(t0), np.concatenate([m for m, _ in pairs]),
                             np.concatenate([i for _, i in pairs]), spans, f_scale=0.01, iterations=30)
    assert np.abs(R[:2] - R_true).max() < 1e-8
    assert np.abs(t[:2] - t_true).max() < 1e-8
    assert np.array_equal(R[2], np.eye(3)) and np.array_equal(t[2], [0.0, 0.0, 1.0])


def test_a_batch_refines_and_associates_each_pose_to_the_same_bits_as_alone():
    """The estimator's results must not depend on which poses share a batch."""
    rng = np.random.default_rng(4)
    R_true = [cv2.Rodrigues(rng.normal(0, 0.5, 3))[0] for _ in range(4)]
    t_true = [np.array([0.0, 0.0, 0.6]) + rng.normal(0, 0.02, 3) for _ in range(4)]
    pairs = [exact_line_matches(rng, n, R, t) for n, R, t in zip((7, 15, 4, 11), R_true, t_true)]
    for m, i in pairs:
        i += rng.normal(0, 0.002, size=i.shape)  # noisy lines: the poses converge slowly
    R0 = np.array([cv2.Rodrigues(rng.normal(0, 0.05, 3))[0] @ R for R in R_true])
    t0 = np.array(t_true) + rng.normal(0, 0.01, (4, 3))
    model, image = np.concatenate([m for m, _ in pairs]), np.concatenate([i for _, i in pairs])
    spans = np.cumsum([0] + [len(m) for m, _ in pairs])
    R, t = refinement.refine_poses(R0, t0, model, image, spans, f_scale=0.002, iterations=3)
    found = refinement.associate_poses(model, spans, R0, t0, image, tolerance=0.01)
    for b, (m, i) in enumerate(pairs):
        R_b, t_b = refinement.refine_poses(R0[b:b + 1], t0[b:b + 1], m, i, np.array([0, len(m)]),
                                             f_scale=0.002, iterations=3)
        assert np.array_equal(R_b[0], R[b]) and np.array_equal(t_b[0], t[b])
        model_index, image_index, distances = nearest_lines(project_normalised(m, R0[b], t0[b]), image, 0.01)
        own = (found[0] >= spans[b]) & (found[0] < spans[b + 1])
        assert np.array_equal(found[0][own] - spans[b], model_index)
        assert np.array_equal(found[1][own], image_index)
        assert np.array_equal(found[2][own], distances)


def reference_nearest_lines(model_2d, image_2d, tolerance, max_angle_deg=10.0):
    """nearest_lines written pair by pair."""
    mi, ii, dist = [], [], []
    for m, (a, b) in enumerate(model_2d):
        length = np.linalg.norm(b - a)
        if length <= 1e-12:
            continue
        unit = (b - a) / length
        normal = np.array([-unit[1], unit[0]])
        best, best_cost = -1, np.inf
        for i, seg in enumerate(image_2d):
            d = seg[1] - seg[0]
            cos = abs(unit @ d) / max(np.linalg.norm(d), 1e-12)
            perp = np.abs((seg - a) @ normal).max()
            along = (seg - a) @ unit
            overlap = min(along.max(), length) - max(along.min(), 0.0)
            if cos > np.cos(np.radians(max_angle_deg)) and perp < tolerance and overlap > 0 and perp < best_cost:
                best, best_cost = i, perp
        if best >= 0:
            mi.append(m), ii.append(best), dist.append(best_cost)
    return np.array(mi, int), np.array(ii, int), np.array(dist)


def test_huber_weights_keep_one_wrong_line_from_pulling_the_pose():
    """16 exact line matches and one line 30 px (at f = 600) off, refined from the true
    pose: Huber weights leave the pose within a third of a millimetre, where plain least
    squares (a threshold nothing exceeds) moves it ten times as far."""
    rng = np.random.default_rng(5)
    R, t = cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))[0], np.array([0.0, 0.0, 0.5])
    model, image = exact_line_matches(rng, 16, R, t)
    image[0] += [0.0, 0.05]
    moved = {}
    for f_scale in (0.002, 1e3):
        R_f, t_f = refinement.refine_poses(R[None], t[None], model, image, np.array([0, 16]), f_scale=f_scale,
                                           iterations=20)
        moved[f_scale] = np.linalg.norm(t_f[0] - t), rotation_angle_deg(R_f[0], R)
    assert moved[0.002][0] < 0.0005 and moved[0.002][1] < 0.1
    assert moved[1e3][0] > 0.002 and moved[1e3][1] > 0.3


def square(center, side):
    corners = np.asarray(center, float) + side / 2 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


def test_a_pose_fitting_only_a_hole_does_not_explain_the_part_around_it():
    """A 60 px window inside a 100 px part: a pose drawing only the window explains its own
    edges, but the outline's margin of at least MIN_MARGIN_PX takes in the part's outer edges
    20 px away, which it does not explain; the whole part's pose explains all."""
    outer, window = square((160, 120), 100), square((160, 120), 60)
    edge_map = np.zeros((240, 320), np.uint8)
    for (x0, y0), (x1, y1) in np.concatenate([outer, window]).astype(int):
        cv2.line(edge_map, (int(x0), int(y0)), (int(x1), int(y1)), 255, 1)
    flat = np.zeros(edge_map.shape, np.float32)
    evidence = scoring.EdgeEvidence(edge_map, flat, flat)
    assert evidence.explained(window, 2.0) < 0.5
    assert evidence.explained(np.concatenate([outer, window]), 2.0) == 1.0


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


def test_nearest_lines_matches_the_pairwise_definition():
    rng = np.random.default_rng(1)
    model = random_segments(rng, 30)
    # image: noisy, shifted, partly cut copies of most model segments plus clutter
    copies = model[:24] + rng.normal(0, 0.01, size=(24, 2, 2))
    copies[::3] = copies[::3, :, :] * [1.0, 0.9]
    image = np.concatenate([copies, random_segments(rng, 15)])[rng.permutation(39)]
    model[5, 1] = model[5, 0]  # a degenerate model segment matches nothing
    got = nearest_lines(model, image, 0.05)
    want = reference_nearest_lines(model, image, 0.05)
    assert len(want[0]) > 15
    for g, w in zip(got, want):
        assert np.allclose(g, w, rtol=0, atol=1e-12)


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
    hull = scoring.EdgeEvidence.grown_outline(pts)
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
        assert evidence.explained(model_px, tolerance) == pytest.approx(
            reference_explained(edge_map, model_px, tolerance), abs=1e-12)


def test_supports_of_a_batch_are_each_pose_alone(evidence_image):
    edge_map, gray, models = evidence_image
    evidence = evidence_of(edge_map, gray)
    spans = np.cumsum([0] + [len(m) for m in models])
    together = evidence.supports(np.concatenate(models), spans, 2.0)
    assert [float(s) for s in together] == [float(evidence.supports(m, np.array([0, len(m)]), 2.0)[0])
                                            for m in models]


def test_polish_pose_pulls_a_pose_three_percent_too_far_onto_the_edge_pixels():
    """A cube's three visible faces drawn in three grey levels: polishing a pose 3 % too
    far away and turned by a degree on the image's Canny pixels recovers the true pose."""
    from brepose_ros.camera import Camera
    from brepose_ros.online.image_edges import detect_edges

    camera = Camera(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480)
    R_true, t_true = cv2.Rodrigues(np.array([0.5, -0.6, 0.3]))[0], np.array([0.01, -0.005, 0.3])
    corners = np.array([[x, y, z] for x in (-0.02, 0.02) for y in (-0.02, 0.02) for z in (-0.02, 0.02)])
    faces = [[0, 1, 3, 2], [4, 5, 7, 6], [0, 1, 5, 4], [2, 3, 7, 6], [0, 2, 6, 4], [1, 3, 7, 5]]
    image = np.full((480, 640), 30, np.uint8)
    segments = []
    visible = [f for f in faces if (R_true @ corners[f].mean(axis=0)) @ (R_true @ corners[f].mean(axis=0) + t_true) < 0]
    for face, grey in zip(visible, (90, 150, 210)):
        cv2.fillConvexPoly(image, np.rint(camera.project_model(corners[face], R_true, t_true)).astype(np.int32), grey)
        segments += [(corners[a], corners[b]) for a, b in zip(face, face[1:] + face[:1])]
    edges = detect_edges(image, EdgeParams())
    evidence = scoring.EdgeEvidence(edges.edge_map, edges.gradient_x, edges.gradient_y)
    R0, t0 = cv2.Rodrigues(np.radians([1.0, 0.0, 0.0]))[0] @ R_true, 1.03 * t_true
    R, t = refinement.polish_pose(R0, t0, np.array(segments), weights=np.ones(len(segments)), evidence=evidence,
                                  camera=camera, radius_px=2.0, rounds=6, spacing_px=3.0, f_scale=1.0 / 600.0,
                                  iterations=3)
    assert np.linalg.norm(t0 - t_true) > 0.008
    # from 9 mm to under 2 mm (measured 1.4): the polygons' corners are rounded to whole pixels
    assert np.linalg.norm(t - t_true) < 0.002
    assert rotation_angle_deg(R, R_true) < 0.5  # from 1 degree (measured 0.4)

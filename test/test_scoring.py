"""Edge evidence (the score's two shares and the polish's pairing) against plain reference
versions and on images with known answers."""
import cv2
import numpy as np
import pytest

from brepose_ros.online import kernels, scoring
from brepose_ros.online.image_edges import (EdgeParams, background_segments, canny_from_gradients, detect_edges,
                                            gradients)
from brepose_ros.online.workers import WorkerPool
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
    outer edges 20 px away, which it does not explain (the window's edges are seen, so the
    cells next to them count); the whole part's pose explains all. With a floor of 10 px the
    margin no longer reaches them."""
    outer, window = square((160, 120), 100), square((160, 120), 60)
    gray = np.full((240, 320), 60, np.float32)
    gray[70:170, 110:210] = 200
    gray[90:150, 130:190] = 60
    evidence = scoring.EdgeEvidence(*edge_stage(gray))
    assert evidence.shares(window, 2.0, MARGIN).explained < 0.5
    assert evidence.shares(window, 2.0, 10.0).explained == 1.0
    assert evidence.shares(np.concatenate([outer, window]), 2.0, MARGIN).explained == 1.0


def l_plate(center, size):
    """An L-shaped plate with a square hole, its outline and the hole's as segments (pixels)."""
    s = size / 4
    outline = np.array([[0, 0], [4, 0], [4, 1.5], [1.5, 1.5], [1.5, 4], [0, 4]]) * s
    hole = np.array([[0.4, 0.4], [1.1, 0.4], [1.1, 1.1], [0.4, 1.1]]) * s
    corners = [c - size / 2 + np.asarray(center, float) for c in (outline, hole)]
    return corners, np.concatenate([np.stack([c, np.roll(c, -1, axis=0)], axis=1) for c in corners])


def turned(segments, degrees):
    center = segments.reshape(-1, 2).mean(axis=0)
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return (segments - center) @ np.array([[c, s], [-s, c]]) + center


def occluded_plate(rng):
    """A bright L plate on a mid-grey background (``l_plate`` at 200 px), its left 30 % (by
    area) under an occluder of random light and dark stripes: the image and the plate's model."""
    gray = np.full((300, 400), 90, np.uint8)
    corners, model = l_plate((200, 150), 200)
    cv2.fillPoly(gray, [np.round(corners[0]).astype(np.int32)], 200)
    cv2.fillPoly(gray, [np.round(corners[1]).astype(np.int32)], 90)
    plate = np.zeros(gray.shape, bool)
    cv2.fillPoly(plate.view(np.uint8), [np.round(corners[0]).astype(np.int32)], 1)
    hidden_columns = np.nonzero(np.cumsum(plate.sum(axis=0)) >= 0.3 * plate.sum())[0][0]
    for x in range(60, hidden_columns, 6):  # the occluder: stripes of random grey
        gray[20:280, x:x + 6] = rng.integers(20, 250)
    for y in range(20, 280, 9):
        gray[y:y + 2, 60:hidden_columns] = rng.integers(20, 250)
    return gray, model


def test_the_truth_outranks_near_poses_with_30_percent_hidden_behind_a_textured_occluder():
    """The occluded plate (``occluded_plate``). The true pose is confirmed beyond chance on 70 % of
    its length and the occluder's edges, where its own edges are missing, do not count
    against it: it scores well above 0.5 and above the same pose shifted by 8 px or turned
    by 8 degrees, which the occluder's stripes confirm here and there."""
    gray, model = occluded_plate(np.random.default_rng(7))
    evidence = scoring.EdgeEvidence(*edge_stage(gray.astype(np.float32)))
    truth = evidence.shares(model, 2.0, MARGIN).score
    assert truth > 0.55
    for wrong in (model + [8.0, 0.0], model + [0.0, 8.0], turned(model, 8.0), turned(model, -8.0)):
        assert evidence.shares(wrong, 2.0, MARGIN).score < truth - 0.25


def test_a_shrunken_copy_on_the_parts_corner_carries_less_evidence_than_the_part_hidden_in_part():
    """The occluded plate, and the plate's model shrunk to 0.6 about its top right corner:
    two of its edges lie on the plate's own, the rest on its bare face. The evidence against
    chance (``surprises_of``, what the larger-pose check compares besides the score) grows
    with the confirmed length: the whole plate, 30 % hidden, carries well over twice the
    shrunken copy's (634 against 140 nats measured), and the plate's edges right of the occluder
    alone carry about as much (682): the hidden length is not what the evidence rests on."""
    gray, model = occluded_plate(np.random.default_rng(7))
    evidence = scoring.EdgeEvidence(*edge_stage(gray.astype(np.float32)))
    corner = model[1, 0]  # the outline's top right corner
    shrunken = corner + 0.6 * (model - corner)

    def surprise(segments):
        return float(evidence.surprises_of(evidence.counts(segments, np.array([0, len(segments)]), 2.0, MARGIN))[0])

    visible = model[model[:, :, 0].min(axis=1) > 150]  # edges right of the occluder
    assert surprise(model) > 2 * surprise(shrunken) > 0
    assert surprise(visible) > 0.8 * surprise(model)


def test_cells_where_the_pose_lies_beside_the_parts_edges_count_against_it_and_hidden_ones_do_not():
    """An L plate and its model shifted 4 px sideways: the vertical edges miss their image
    edges at the look-up tolerance, and with the cells seen only there (``pose.seen_pixels``
    off) their unexplained image edges would not count. Beside them within the default
    ``pose.seen_pixels``, they do: the explained share falls from 0.93 to about half. With the
    plate's left 30 % under a plain occluder the hidden edges have no image edge beside them,
    and the truth's score stays within 0.02."""
    gray = np.full((300, 400), 90, np.uint8)
    corners, model = l_plate((200, 150), 200)
    cv2.fillPoly(gray, [np.round(corners[0]).astype(np.int32)], 200)
    cv2.fillPoly(gray, [np.round(corners[1]).astype(np.int32)], 90)
    hidden = gray.copy()
    hidden[:, :160] = 30

    def shares(image, pose, seen_pixels=PoseParams().seen_pixels):
        return scoring.EdgeEvidence(*edge_stage(image.astype(np.float32))).shares(pose, 2.0, MARGIN,
                                                                                   seen_tolerance_px=seen_pixels)

    beside, occluded = shares(gray, model + [4.0, 0.0]), shares(hidden, model)
    assert beside.explained < shares(gray, model + [4.0, 0.0], seen_pixels=0.0).explained - 0.3
    assert occluded.score == pytest.approx(shares(hidden, model, seen_pixels=0.0).score, abs=0.02)


def l_plate_on_a_ruled_table(rows=50):
    """A bright L plate with a square hole (160 px, ``l_plate``) on a grey table ruled with
    ``rows`` dark lines 2 px wide, 24 px apart at 30 degrees, across the whole 640 x 480 image
    (50 fill it): the plate stands in front of them, its hole shows them. The image and the
    plate's model segments (pixels)."""
    table = np.full((480, 640), 120, np.uint8)
    along = np.array([np.cos(np.radians(30)), np.sin(np.radians(30))])
    for offset in range(-24 * (rows // 2), 24 * (rows - rows // 2), 24):
        centre = np.array([320.0, 240.0]) + offset * np.array([-along[1], along[0]])
        ends = np.rint([centre - 900 * along, centre + 900 * along]).astype(int)
        cv2.line(table, tuple(map(int, ends[0])), tuple(map(int, ends[1])), 70, 2, cv2.LINE_AA)
    corners, model = l_plate((320, 240), 160)
    gray = table.copy()
    cv2.fillPoly(gray, [np.round(corners[0]).astype(np.int32)], 210)
    hole = np.zeros(gray.shape, np.uint8)
    cv2.fillPoly(hole, [np.round(corners[1]).astype(np.int32)], 1)
    gray[hole > 0] = table[hole > 0]
    return gray, model


def test_lines_ruled_across_the_table_are_not_the_parts_edges_and_do_not_sink_it():
    """The ruled lines' pieces on either side of the plate (and in its hole) join into lines
    reaching across more than 0.4 of the image's diagonal (``edges.background_line_fraction``),
    eight or more of them parallel (``edges.background_pattern_lines``), while no edge of the
    plate is that long: the edge stage drops their pixels, over half of the
    image's, and of the pixels on the plate's outline only the lines' own ends meeting it.
    Kept (fraction 0), they sink the true pose's explained share below 0.6; dropped, it is
    above 0.9 and the truth scores above ``pose.min_score``, while a pose drawing only the
    plate's hole still does not explain the plate around it and a pose turned 8 degrees
    scores well below the truth. Three ruled lines, six edges that long, are no pattern (a
    long rod in front shows as many), and nothing is dropped."""
    gray, model = l_plate_on_a_ruled_table()
    kept, cleared = detect_edges(gray, EdgeParams(background_line_fraction=0.0)), detect_edges(gray, EdgeParams())
    assert len(background_segments(kept.segments, float(np.hypot(*gray.shape)), EdgeParams())) >= 8
    dropped = (kept.edge_map > 0) & (cleared.edge_map == 0)
    assert not ((cleared.edge_map > 0) & (kept.edge_map == 0)).any() and dropped.sum() > 0.5 * (kept.edge_map > 0).sum()
    outline = np.zeros(gray.shape, np.uint8)
    cv2.polylines(outline, [np.rint(segment).astype(np.int32) for segment in model], False, 1, 3)
    on_outline = (outline > 0) & (kept.edge_map > 0)  # the plate's edge pixels and the lines' ends meeting them
    assert (dropped & on_outline).sum() < 0.05 * on_outline.sum()

    def evidence(edges):
        return scoring.EdgeEvidence(edges.edge_map, edges.gradient_x, edges.gradient_y)

    assert evidence(kept).shares(model, 2.0, MARGIN).explained < 0.6
    truth = evidence(cleared).shares(model, 2.0, MARGIN)
    assert truth.explained > 0.9 and truth.score > PoseParams().min_score
    assert evidence(cleared).shares(model[6:], 2.0, MARGIN).explained < 0.5  # the hole's four edges alone
    assert evidence(cleared).shares(turned(model, 8.0), 2.0, MARGIN).score < truth.score - 0.25
    three, _ = l_plate_on_a_ruled_table(rows=3)
    assert np.array_equal(detect_edges(three, EdgeParams()).edge_map,
                          detect_edges(three, EdgeParams(background_line_fraction=0.0)).edge_map)
    assert not np.array_equal(detect_edges(three, EdgeParams(background_pattern_lines=6)).edge_map,
                              detect_edges(three, EdgeParams(background_line_fraction=0.0)).edge_map)


def test_a_pose_too_far_on_pieces_of_the_parts_edges_is_told_by_the_edges_running_on():
    """An L plate, and the same model 1.5x as far (scaled by 1 / 1.5 about the plate's outer
    corner, so two of its edges lie on pieces of the plate's): beyond their ends the plate's
    edges run on, in line and alike, where the model has none; the truth's ends show no
    run-on, nor with 30 % of the plate hidden (occlusion cuts edges short). The run-on lowers
    the far pose's score, not the truth's. The model 1.5x as near finds no edge beyond its
    ends (its tails are unconfirmed instead)."""
    gray = np.full((300, 400), 90, np.uint8)
    corners, model = l_plate((200, 150), 200)
    cv2.fillPoly(gray, [np.round(corners[0]).astype(np.int32)], 200)
    cv2.fillPoly(gray, [np.round(corners[1]).astype(np.int32)], 90)
    corner = corners[0][0]
    far, near = corner + (model - corner) / 1.5, corner + (model - corner) * 1.5
    hidden = gray.copy()
    hidden[:, :160] = 30  # a plain occluder over the plate's left 30 %
    for image in (gray, hidden):
        evidence = scoring.EdgeEvidence(*edge_stage(image.astype(np.float32)))
        truth, wrong = evidence.shares(model, 2.0, MARGIN), evidence.shares(far, 2.0, MARGIN)
        assert truth.run_on < 0.02 and wrong.run_on > truth.run_on + 0.05
        assert wrong.score == pytest.approx(wrong._replace(run_on=0.0).score
                                            * (1 - scoring.EdgeEvidence.RUN_ON_WEIGHT * wrong.run_on))
        assert truth.score == truth._replace(run_on=0.0).score
    evidence = scoring.EdgeEvidence(*edge_stage(gray.astype(np.float32)))
    assert evidence.shares(far, 2.0, MARGIN).run_on > 0.1
    assert evidence.shares(near, 2.0, MARGIN).run_on < 0.02


#: the window of maps over the whole 240 x 320 image with its border
WHOLE = np.array([0, 0, 240, 320], np.int64)


def test_the_run_on_kernel_counts_probes_beyond_ends_off_other_model_edges():
    """Against a plain count: one horizontal model edge from x 100 to 140 on an image edge
    from 60 to 200. Its probes reach 0.25 x 40 = 10 px past each end from 4 px out (clear 3):
    20 points, all on the image edge; a second model edge crossing one probe's path takes the
    points within 3 px of it out (and adds its own probes); a model edge 4 px long has none."""
    near = np.zeros((1, 8, 242, 322), np.uint8)
    near[0, :, 120 + 1, 60 + 1:200 + 1] = 1
    chance = np.zeros(near.shape, np.float32)
    out = np.zeros((3, 3))
    edge = np.array([[[100.0, 120.0], [140.0, 120.0]]])
    crossing = np.array([[[150.0, 100.0], [150.0, 140.0]]])
    short = np.array([[[100.0, 120.0], [104.0, 120.0]]])
    kernels.run_on_kernel(np.concatenate([edge, edge, crossing, short]), np.array([0, 1, 3, 4]), near, chance,
                          WHOLE, 0.25, 6.0, 30.0, 10.0, 3.0, out)
    assert out[0].tolist() == [20.0, 20.0, 0.0]
    # right of the end (x 144-153) the points within 3 px of x = 150 (147-153) are the model's;
    # the crossing edge's own 20 probes (above and below it) find no image edge
    assert out[1].tolist() == [33.0, 13.0, 0.0]
    assert out[2].tolist() == [0.0, 0.0, 0.0]


def test_a_model_edge_off_the_image_hides_no_run_on_probe_inside_it():
    """The model's pixels are drawn within the image only: an edge 2 px above the top row
    (x 140-160) does not hide the probes of an edge along the top row (x 100-140), whose 10
    probes past each end all count and lie on the image edge; its own probes lie outside."""
    near = np.zeros((1, 8, 242, 322), np.uint8)
    near[0, :, 0 + 1, 60 + 1:200 + 1] = 1
    chance = np.zeros(near.shape, np.float32)
    out = np.zeros((1, 3))
    segments = np.array([[[100.0, 0.0], [140.0, 0.0]], [[140.0, -2.0], [160.0, -2.0]]])
    kernels.run_on_kernel(segments, np.array([0, 2]), near, chance, WHOLE, 0.25, 6.0, 30.0, 10.0, 3.0, out)
    assert out[0].tolist() == [20.0, 20.0, 0.0]


def test_outlines_of_curved_faces_are_looked_up_within_their_own_reach():
    """A disc whose image edge lies 3 px inside the model's outline (a soft silhouette: the
    curved face darkens towards it) beside a plate whose sharp edges lie on the model's. At
    the sharp edges' 2 px the outline goes unconfirmed and the truth scores below 0.5; with
    the outline marked soft and looked up within 3.5 px the model is confirmed beyond 0.95
    (the disc's edge pixels, 3 px off, still count as unexplained) and the truth scores
    above 0.6, while the same model 4 or 8 px to the side stays below 0.4 and the plate's
    edges, not soft, are not confirmed 4 px off."""
    gray = np.full((240, 320), 60, np.float32)
    cv2.circle(gray, (110, 120), 47, 200, -1)
    gray[80:160, 190:270] = 200
    angles = np.linspace(0, 2 * np.pi, 49)
    ring = np.stack([110 + 50 * np.cos(angles), 120 + 50 * np.sin(angles)], axis=1)
    disc, plate = np.stack([ring[:-1], ring[1:]], axis=1), square((229.5, 119.5), 80)
    model, soft = np.concatenate([disc, plate]), np.arange(len(disc) + len(plate)) < len(disc)
    evidence = scoring.EdgeEvidence(*edge_stage(gray))
    assert evidence.shares(model, 2.0, MARGIN).score < 0.5
    assert evidence.shares(model, 2.0, MARGIN, soft, 2.0).score == evidence.shares(model, 2.0, MARGIN).score
    truth = evidence.shares(model, 2.0, MARGIN, soft, 3.5)
    assert truth.confirmed > 0.95 and truth.score > 0.6
    for shift in (4.0, 8.0):
        assert evidence.shares(model + [shift, 0.0], 2.0, MARGIN, soft, 3.5).score < 0.4
    assert evidence.shares(plate + [4.0, 0.0], 2.0, MARGIN, np.zeros(4, bool), 3.5).confirmed < 0.5


def test_a_pose_in_dense_random_clutter_scores_near_zero():
    """Dense random strokes, no part: plain support confirms a fifth or more of a square's
    edges by chance, the share beyond chance stays below 0.2 and the score near 0."""
    rng = np.random.default_rng(11)
    gray = np.full((300, 400), 128, np.uint8)
    for _ in range(500):
        (x0, y0), angle = rng.uniform([0, 0], [400, 300]), rng.uniform(0, np.pi)
        length = rng.uniform(10, 40)
        cv2.line(gray, (int(x0), int(y0)), (int(x0 + length * np.cos(angle)), int(y0 + length * np.sin(angle))),
                 int(rng.integers(0, 256)), 1)
    evidence = scoring.EdgeEvidence(*edge_stage(gray.astype(np.float32)))
    poses = [square((x, y), side) for x in (150, 200, 250) for y in (120, 150, 180) for side in (80, 120)]
    chance = [evidence.supports(pose, np.array([0, 4]), 2.0)[0] for pose in poses]
    assert np.mean(chance) > 0.2  # what chance alone confirms
    for pose in poses:
        shares = evidence.shares(pose, 2.0, MARGIN)
        assert shares.confirmed < 0.2 and shares.score < 0.05


def test_an_edge_pixel_pairs_with_a_model_point_only_if_it_runs_alike():
    """The edge alignment's pairing (kernels.nearest_like_edge): a point 2 px below a
    horizontal image edge finds it for a horizontal model edge, not for a vertical one."""
    gray = np.full((240, 320), 50, np.float32)
    gray[120:] = 200
    evidence = scoring.EdgeEvidence(*edge_stage(gray))
    horizontal, vertical = evidence.orientation_bin(np.array([[[0.0, 0.0], [1.0, 0.0]], [[0.0, 0.0], [0.0, 1.0]]]))
    assert kernels.nearest_like_edge(*evidence.nearest_like(), horizontal, 200.0, 121.0, 2.0) == (True, 200.0, 119.0)
    assert not kernels.nearest_like_edge(*evidence.nearest_like(), vertical, 200.0, 121.0, 2.0)[0]


def test_chance_is_the_share_of_near_pixels_in_the_window_to_the_bit():
    """EdgeEvidence.chance (the window's counts of the uint8 map divided in float32) equals
    the normalised box filter of the map made float, bit for bit, border and all: the
    scores were measured on that filter. OpenCV's normalised filter straight from uint8
    rounds some shares differently, so a like-for-like swap would have failed here."""
    evidence = scoring.EdgeEvidence(*edge_stage(random_lines(5, (240, 320), 60)))
    window = (scoring.EdgeEvidence.CHANCE_WINDOW,) * 2
    near, chance = whole(evidence.maps((2.0,)))
    assert len(np.unique(chance)) > 100  # many counts, sparse to dense
    for b in range(scoring.EdgeEvidence.BINS):
        share = cv2.boxFilter(near[b, 1:-1, 1:-1].astype(np.float32), -1, window, borderType=cv2.BORDER_REFLECT)
        assert np.array_equal(chance[b, 1:-1, 1:-1].view(np.int32), share.view(np.int32))
    assert not chance[:, 0].any() and not chance[:, :, -1].any()


def horizontal_band(shape):
    """A float32 gray image of a bright band across its whole width: horizontal edges only."""
    gray = np.full(shape, 80, np.float32)
    gray[shape[0] // 3: shape[0] // 2] = 200
    return gray


@pytest.mark.parametrize("picture", ["lines", "band"])
def test_maps_built_per_bin_on_threads_equal_those_built_on_first_use(monkeypatch, picture):
    """EdgeEvidence.bin_jobs / adopt (Frame.detect's split of the maps over the worker
    threads) give the nearest-edge table and the maps at each tolerance to the bit, with
    the maps' memory holding garbage before the jobs (``bin_jobs`` leaves it unset); the
    band's edges leave bins without pixels."""
    stage = edge_stage(random_lines(4, (240, 320), 60) if picture == "lines" else horizontal_band((240, 320)))
    prepared, lazy = scoring.EdgeEvidence(*stage), scoring.EdgeEvidence(*stage)
    assert prepared.like_edges.any(axis=(1, 2)).all() == (picture == "lines")
    pool = WorkerPool(2)
    try:
        with monkeypatch.context() as patch:
            patch.setattr(scoring.np, "empty", lambda shape, dtype: np.full(shape, 77, dtype))
            jobs = prepared.bin_jobs((2.0, 3.0))
        prepared.adopt(pool.map(lambda job: job(), jobs))
    finally:
        pool.close()
    for ours, theirs in zip(prepared.nearest_like(3.0), lazy.nearest_like(3.0)):
        assert np.array_equal(ours, theirs)
    ours, theirs = prepared.maps((2.0, 3.0)), lazy.maps((2.0, 3.0))
    assert ours.tolerances == theirs.tolerances
    for mine, lazily in zip(ours[1:], theirs[1:]):
        assert np.array_equal(mine, lazily)


def test_the_nearest_edge_table_names_each_pixels_nearest_like_edge_pixel():
    """EdgeEvidence.nearest_like: per bin, every pixel's entry is a like edge pixel, the one
    OpenCV's labelled distance transform assigns (its labels looked up in the like map
    itself, as a plain reference), and that pixel is as near as the nearest to within the
    5x5 chamfer's few per cent."""
    evidence = scoring.EdgeEvidence(*edge_stage(random_lines(5, (120, 160), 25)))
    labels, origin, table = evidence.nearest_like()
    assert labels.shape == (evidence.BINS, 120, 160) and not origin.any()
    rows, cols = np.mgrid[:120, :160]
    for b in range(evidence.BINS):
        like = evidence.like_edges[b]
        nearest = table[labels[b]]
        assert like[nearest[..., 1].astype(int), nearest[..., 0].astype(int)].all()
        reference_labels = cv2.distanceTransformWithLabels(1 - like, cv2.DIST_L2, 5,
                                                           labelType=cv2.DIST_LABEL_PIXEL)[1]
        by_label = np.zeros((reference_labels.max() + 1, 2))
        by_label[reference_labels[like > 0]] = np.stack([cols[like > 0], rows[like > 0]], axis=1)
        assert np.array_equal(nearest, by_label[reference_labels])
        exact = cv2.distanceTransform(1 - like, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        assert (np.hypot(nearest[..., 0] - cols, nearest[..., 1] - rows) <= 1.05 * exact + 1e-6).all()


@pytest.mark.parametrize("picture", ["centre", "corner", "bottom right", "lines", "band", "blank"])
@pytest.mark.parametrize("reach", [2.0, 6.0, 20.0])
def test_nearest_edges_over_their_window_are_the_whole_images_and_pair_alike(picture, reach):
    """EdgeEvidence.nearest_like(reach) labels the edge pixels' box grown by the reach: there
    the labels are the whole image's transform's to the bit (the proof in its doc), and a
    point anywhere in or near the image, paired within any radius up to the reach
    (kernels.nearest_like_edge), pairs with the same edge pixel or none as on the whole
    image's labels. A window over more than WHOLE_LABELS_SHARE of the image is the whole."""
    shape = (240, 320)
    gray = {"centre": a_part_and_specks(shape, 60, []), "corner": a_part_and_specks(shape, 40, [(1, 2)]),
            "bottom right": a_part_and_specks(shape, 40, [(318, 237), (300, 239)]),
            "lines": random_lines(7, shape, 4), "band": horizontal_band(shape),
            "blank": np.full(shape, 90, np.float32)}[picture]
    stage = edge_stage(gray)
    windowed, whole_image = scoring.EdgeEvidence(*stage), scoring.EdgeEvidence(*stage)
    labels, origin, table = windowed.nearest_like(reach)
    all_labels, all_origin, all_table = whole_image.nearest_like()
    assert np.array_equal(table, all_table) and not all_origin.any()
    (top, left), (rows, cols) = origin, labels.shape[1:]
    assert np.array_equal(labels, all_labels[:, top:top + rows, left:left + cols])
    if picture == "centre":
        assert rows * cols < 0.3 * shape[0] * shape[1]
    if picture == "lines":
        assert rows * cols == shape[0] * shape[1]  # spread over the image: the whole
    rng = np.random.default_rng(2)
    for u, v, direction, radius in zip(rng.uniform(-3, shape[1] + 3, 3000), rng.uniform(-3, shape[0] + 3, 3000),
                                       rng.integers(0, windowed.BINS, 3000), rng.uniform(0.5, reach, 3000)):
        mine = kernels.nearest_like_edge(labels, origin, table, direction, u, v, radius)
        theirs = kernels.nearest_like_edge(all_labels, all_origin, all_table, direction, u, v, radius)
        assert mine[0] == theirs[0] and (not mine[0] or mine == theirs)  # where none pairs, the pixel is unused


def test_nearest_edges_reach_wider_when_asked():
    """A wider reach than the table has builds it again over a wider window (the whole
    image without a reach); a narrower one keeps it."""
    evidence = scoring.EdgeEvidence(*edge_stage(a_part_and_specks((240, 320), 60, [])))
    narrow = evidence.nearest_like(2.0)
    assert evidence.nearest_like(1.0) is narrow
    wider = evidence.nearest_like(10.0)
    assert wider.labels.shape[1] == narrow.labels.shape[1] + 16
    assert evidence.nearest_like().labels.shape[1:] == (240, 320)


def random_lines(seed, shape, count):
    """A float32 gray image of ``count`` random bright lines, 2 px wide, on a dark ground."""
    rng = np.random.default_rng(seed)
    gray = np.full(shape, 80, np.uint8)
    for _ in range(count):
        (x0, y0), (x1, y1) = rng.uniform([0, 0], [shape[1], shape[0]], size=(2, 2))
        cv2.line(gray, (int(x0), int(y0)), (int(x1), int(y1)), int(rng.integers(150, 256)), 2)
    return gray.astype(np.float32)


def edge_stage(gray):
    """Canny's edge map and the gradient it ran on, at the default edge parameters."""
    dx, dy = gradients(gray, EdgeParams())
    return canny_from_gradients(dx, dy, EdgeParams()), dx, dy


def whole(maps, layer=0):
    """One layer of ``LookUpMaps`` over the whole image with its border, 0 outside their window."""
    top, left, h, w = maps.window
    rows, cols = maps.near.shape[2:]
    near = np.zeros((scoring.EdgeEvidence.BINS, h + 2, w + 2), np.uint8)
    chance = np.zeros(near.shape, np.float32)
    near[:, top:top + rows, left:left + cols] = maps.near[layer]
    chance[:, top:top + rows, left:left + cols] = maps.chance[layer]
    return near, chance


def whole_image_maps(evidence, tolerance):
    """The look-up maps by their definition, on the whole image: per bin the like edges
    dilated by the chamfer ball, and the share of such pixels in the chance window (the box
    filter's border reflected), with a border of 0."""
    h, w = evidence.shape
    near = np.zeros((evidence.BINS, h + 2, w + 2), np.uint8)
    chance = np.zeros(near.shape, np.float32)
    window = (evidence.CHANCE_WINDOW,) * 2
    for b in range(evidence.BINS):
        near[b, 1:-1, 1:-1] = cv2.dilate(evidence.like_edges[b], scoring.chamfer_ball(tolerance))
        chance[b, 1:-1, 1:-1] = cv2.boxFilter(near[b, 1:-1, 1:-1].astype(np.float32), -1, window,
                                              borderType=cv2.BORDER_REFLECT)
    return near, chance


def a_part_and_specks(shape, part, specks):
    """A float32 gray image: a bright square of side ``part`` at the centre and ``specks``
    (x, y) small dark squares, e.g. by the image's edges."""
    gray = np.full(shape, 90, np.uint8)
    cy, cx = shape[0] // 2, shape[1] // 2
    gray[cy - part // 2:cy + part // 2, cx - part // 2:cx + part // 2] = 220
    for x, y in specks:
        gray[max(y - 2, 0):y + 3, max(x - 2, 0):x + 3] = 10
    return gray.astype(np.float32)


@pytest.mark.parametrize("picture", ["centre", "corner", "bottom right", "lines", "band", "blank"])
@pytest.mark.parametrize("tolerances", [(2.0,), (2.0, 6.0), (1.0, 3.5, 6.0)])
def test_look_up_maps_over_their_window_are_the_whole_images_maps(picture, tolerances):
    """EdgeEvidence.maps builds the maps over the edge pixels' box grown by the widest
    tolerance's reach and half the chance window: expanded to the whole image they are the
    maps by their definition to the bit, for edges far from the image's sides (the window a
    small part of it), by a corner or a side (the window clipped there: the box filter
    reflects at the image's side as before), across the image, without edges in some bins
    or at all; a look-up clipped into the window reads the whole image's value anywhere."""
    shape = (240, 320)
    gray = {"centre": a_part_and_specks(shape, 60, []), "corner": a_part_and_specks(shape, 40, [(1, 2)]),
            "bottom right": a_part_and_specks(shape, 40, [(318, 237), (300, 239)]),
            "lines": random_lines(6, shape, 20), "band": horizontal_band(shape),
            "blank": np.full(shape, 90, np.float32)}[picture]
    evidence = scoring.EdgeEvidence(*edge_stage(gray))
    maps = evidence.maps(tolerances)
    if picture == "centre":
        assert maps.near.shape[2] * maps.near.shape[3] < 0.3 * (shape[0] + 2) * (shape[1] + 2)
    rng = np.random.default_rng(1)
    x, y = rng.integers(0, shape[1] + 2, 5000), rng.integers(0, shape[0] + 2, 5000)
    bins = rng.integers(0, evidence.BINS, 5000)
    for layer, tolerance in enumerate(tolerances):
        near, chance = whole_image_maps(evidence, tolerance)
        mine, my_chance = whole(maps, layer)
        assert np.array_equal(mine, near) and np.array_equal(my_chance.view(np.int32), chance.view(np.int32))
        if layer == 0:
            looked_up, looked_up_chance = maps.at(bins, x, y)
            assert np.array_equal(looked_up, near[bins, y, x] != 0)
            assert np.array_equal(looked_up_chance, chance[bins, y, x])


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


def reference_shares(evidence, model_px, tolerance, seen_tolerance):
    """EdgeEvidence.shares' two shares by their definitions, in plain numpy on whole-image
    arrays: the chance-corrected share, the seen cells (also at ``seen_tolerance`` when wider
    than ``tolerance``), the outline row by row, the model drawn as points a pixel apart
    grown by the tolerance."""
    h, w = evidence.shape
    model_px = np.clip(model_px, -4.0 * max(h, w), 5.0 * max(h, w))
    near, chance = whole_image_maps(evidence, tolerance)
    seen_tolerance = max(seen_tolerance, tolerance)  # no wider: the look-up tolerance's test again
    wide, wide_chance = whole_image_maps(evidence, seen_tolerance)
    cell, reach = evidence.SEEN_CELL, evidence.SEEN_REACH
    rows, cols = -(-h // cell), -(-w // cell)
    model_in, confirmed_in, chance_in, wide_in, wide_chance_in = np.zeros((5, rows, cols))
    length = confirmed = by_chance = 0.0
    for seg, own in zip(model_px, evidence.orientation_bin(model_px)):
        count = int(np.clip(np.ceil(np.linalg.norm(seg[1] - seg[0]) / 2.0), 1, 2000))
        weight = np.linalg.norm(seg[1] - seg[0]) / count
        for k in range(count):
            x, y = np.clip(np.rint(seg[0] + (k + 0.5) / count * (seg[1] - seg[0])).astype(int) + 1, 0, [w + 1, h + 1])
            length += weight
            by_chance += weight * chance[own, y, x]
            confirmed += weight * near[own, y, x]
            if 1 <= x <= w and 1 <= y <= h:
                at = ((y - 1) // cell, (x - 1) // cell)
                model_in[at] += weight
                confirmed_in[at] += weight * near[own, y, x]
                chance_in[at] += weight * chance[own, y, x]
                wide_in[at] += weight * wide[own, y, x]
                wide_chance_in[at] += weight * wide_chance[own, y, x]
    seen = np.zeros((rows, cols), bool)
    for r in range(rows):
        for c in range(cols):
            around = np.s_[max(r - reach, 0):r + reach + 1, max(c - reach, 0):c + reach + 1]
            at = (r, c) if model_in[r, c] > 0 else around
            seen[r, c] = model_in[at].sum() > 0 and (
                confirmed_in[at].sum() - chance_in[at].sum() >= 0.5 * model_in[at].sum()
                or wide_in[at].sum() - wide_chance_in[at].sum() >= 0.5 * model_in[at].sum())
    outline = evidence.grown_outline(model_px.reshape(-1, 2), MARGIN)
    inside = np.zeros((h, w), bool)
    for y in range(h):
        a, b = outline, np.roll(outline, -1, axis=0)
        crossing = ((a[:, 1] <= y) & (y < b[:, 1])) | ((b[:, 1] <= y) & (y < a[:, 1]))
        if crossing.any():
            a, b = a[crossing], b[crossing]
            x = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
            inside[y, max(int(np.ceil(x.min())), 0):max(int(np.floor(x.max())) + 1, 0)] = True
    inside &= evidence.edges & np.kron(seen, np.ones((cell, cell), bool))[:h, :w]
    drawn = np.zeros((h, w), bool)
    radius = int(tolerance)
    ball = [(ox, oy) for oy in range(-radius, radius + 1) for ox in range(-radius, radius + 1)
            if ox * ox + oy * oy <= tolerance * tolerance]
    for seg in model_px:
        count = int(np.clip(np.ceil(np.linalg.norm(seg[1] - seg[0])), 1, 4000))
        for x, y in np.rint(seg[0] + np.arange(count + 1)[:, None] / count * (seg[1] - seg[0])).astype(int):
            for ox, oy in ball:
                if 0 <= x + ox < w and 0 <= y + oy < h:
                    drawn[y + oy, x + ox] = True
    return (max(confirmed - by_chance, 0) / (length - by_chance),
            (drawn & inside).sum() / inside.sum() if inside.any() else 0.0)


@pytest.mark.parametrize("seen_tolerance", [0.0, 6.0])
@pytest.mark.parametrize("tolerance", [1.0, 2.0, 3.5])
def test_edge_evidence_matches_the_distance_transform_definitions(evidence_image, tolerance, seen_tolerance):
    edge_map, gray, models = evidence_image
    evidence = evidence_of(edge_map, gray)
    for model_px in models:
        assert evidence.supports(model_px, np.array([0, len(model_px)]), tolerance)[0] == pytest.approx(
            reference_support(edge_map, gray, model_px, tolerance), abs=1e-12)
        shares = evidence.shares(model_px, tolerance, MARGIN, seen_tolerance_px=seen_tolerance)
        reference = reference_shares(evidence, model_px, tolerance, seen_tolerance)
        assert shares.confirmed == pytest.approx(reference[0], abs=1e-5)
        assert shares.explained == pytest.approx(reference[1], abs=1e-12)


def test_counted_pixels_are_what_the_explained_share_counts(evidence_image):
    """The picture of a pose's counted edge pixels (bench/explained_overlay.py) holds only
    edge pixels, and its explained ones over all counted are the explained share."""
    edge_map, gray, models = evidence_image
    evidence = evidence_of(edge_map, gray)
    for model_px in models:
        labels = evidence.counted_pixels(model_px, 2.0, MARGIN)
        assert not (labels[edge_map == 0]).any()
        counted = (labels > 0).sum()
        assert counted > 0
        assert (labels == 2).sum() / counted == evidence.shares(model_px, 2.0, MARGIN).explained


def test_supports_of_a_batch_are_each_pose_alone(evidence_image):
    edge_map, gray, models = evidence_image
    evidence = evidence_of(edge_map, gray)
    spans = np.cumsum([0] + [len(m) for m in models])
    together = evidence.supports(np.concatenate(models), spans, 2.0)
    assert [float(s) for s in together] == [float(evidence.supports(m, np.array([0, len(m)]), 2.0)[0])
                                            for m in models]


def test_scores_of_a_batch_are_each_poses_shares_score_to_the_bit():
    rng = np.random.default_rng(3)
    n = 5000
    length, seen, probes = rng.uniform(50, 3000, n), rng.integers(0, 400, n), rng.integers(0, 200, n)
    counts = np.stack([length, rng.random(n) * length, rng.random(n) * 0.3 * length, seen,
                       np.floor(rng.random(n) * seen), probes, np.floor(rng.random(n) * probes),
                       rng.random(n) * 0.3 * probes], axis=1)
    counts[::5, 0] = 0.0  # no model length: zeros
    counts[::7, 3] = counts[::7, 4] = 0.0  # no edge pixel seen
    counts[::11, 1] = counts[::11, 2]  # confirmed exactly as chance would
    counts[::13, 1] = counts[::13, 0]  # all confirmed: the capped share
    counts[::17, 5:] = 0.0  # no run-on probe
    evidence = scoring.EdgeEvidence.__new__(scoring.EdgeEvidence)  # scores_of reads the class's constants only
    scores = evidence.scores_of(counts)
    assert np.count_nonzero(scores) > n // 2
    assert scores.tobytes() == np.array([evidence.shares_of(c).score for c in counts]).tobytes()
    # the evidence in nats is the significance's exponent
    significance = np.array([evidence.shares_of(c).significance for c in counts])
    surprises = evidence.surprises_of(counts)
    assert np.all(surprises[counts[:, 0] == 0] == 0) and np.all(surprises >= 0)
    assert np.allclose(1.0 - np.exp(-surprises / evidence.SIGNIFICANT_PIXELS), significance, rtol=0, atol=1e-12)

"""Candidate regions and the views are normalised alike, by their outline; segment clusters."""
import numpy as np
import pytest

from brepose_ros.camera import Camera
from brepose_ros.online.frame import Frame
from brepose_ros.online.hypotheses import ViewLibrary
from brepose_ros.online.regions import cluster_segments, normalised_region
from brepose_ros.online.scoring import EdgeEvidence
from brepose_ros.params import MatchParams
from graph_helpers import one_view_graph

CAMERA = Camera.from_fov(640, 480, 600.0)


def square(center, side):
    """The four sides (4, 2, 2) of an axis-aligned square."""
    corners = np.asarray(center, float) + side / 2 * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)


#: an inner edge off the centre: it moves a length-weighted centroid, not the outline's
INNER = np.array([[[30.0, 10.0], [30.0, 60.0]]])


def frame_of(segments_px):
    """A frame of these segments, without edge pixels."""
    empty = np.zeros((CAMERA.height, CAMERA.width), np.float32)
    return Frame(segments_px=segments_px, segments_n=CAMERA.undistort(segments_px),
                 refine_segments_n=CAMERA.undistort(segments_px), camera=CAMERA,
                 evidence=EdgeEvidence(empty.astype(np.uint8), empty, empty), edge_points_n=np.zeros((0, 2)))


def test_a_region_is_normalised_by_its_outline_whatever_its_inner_edges():
    outline = square((CAMERA.cx, CAMERA.cy), 180.0)
    with_inner = np.concatenate([outline, INNER + [CAMERA.cx, CAMERA.cy]])
    regions = [normalised_region(np.arange(len(s)), frame_of(s), MatchParams()) for s in (outline, with_inner)]
    for region in regions:
        assert region.scale == pytest.approx(180.0 / 600.0)  # the square root of the outline's area
        assert np.allclose(region.center, 0.0, atol=1e-12)
    assert np.array_equal(regions[0].features.segments, regions[1].features.segments[:4])


def test_a_view_is_normalised_by_its_outline_whatever_its_inner_edges():
    outline = square((0.02, -0.01), 0.04)
    library = ViewLibrary(one_view_graph(np.concatenate([outline, INNER * 2e-4 + [0.02, -0.01]])), max_segments=60)
    norm = library.normalisation[0]
    assert norm.scale == pytest.approx(0.04, rel=1e-6)
    assert np.allclose(norm.center, [0.02, -0.01], atol=1e-8)


def test_clusters_are_chains_of_close_end_points_largest_first():
    big, small = square((100.0, 100.0), 120.0), square((400.0, 300.0), 60.0)
    speck = np.array([[[600.0, 50.0], [600.0, 58.0]]])  # under a tenth of the largest cluster's length
    segments = np.concatenate([small, speck, big])
    clusters = cluster_segments(segments, gap=5.0)
    assert [sorted(c.tolist()) for c in clusters] == [[5, 6, 7, 8], [0, 1, 2, 3]]
    assert cluster_segments(big, gap=5.0) == []  # one cluster is the whole image again
    apart = big.copy()
    apart[2] += [0.0, 6.0]  # the top side moved away by more than the gap: two clusters
    assert len(cluster_segments(apart, gap=5.0)) == 2


def test_two_segments_chain_through_whichever_of_their_ends_are_close():
    """Segment 1 has only its end ``b`` within the gap of segment 0's end ``a``, for each of
    the four pairings: the two are one cluster, a far segment another."""
    far = np.array([[500.0, 500.0], [512.0, 500.0]])
    for a in (0, 1):
        for b in (0, 1):
            first = np.array([[0.0, 0.0], [12.0, 0.0]])
            second = np.array([[0.0, 30.0], [0.0, 30.0]])  # pointing away from the first, from its end b
            second[b] = first[a] + [0.0, 2.0]
            second[1 - b] = first[a] + [0.0, 14.0]
            clusters = cluster_segments(np.stack([first, second, far]), gap=5.0)
            assert [c.tolist() for c in clusters] == [[0, 1], [2]], (a, b)


def test_a_seed_is_matched_in_its_own_frame_and_corrected_whatever_lies_outside_its_window():
    """An L-shaped part drawn at a known similarity, clutter far off to one side (it would
    move a hull normalisation of the whole image): a seed 9 degrees, 12 % in size and 15 px
    off is pulled onto the truth by Kuhn-Munkres in the seed's own frame."""
    from brepose_ros.online.hypotheses import Hypothesis, TetradHypotheses
    from brepose_ros.online.search import _seed_region
    from brepose_ros.online.workers import SERIAL
    from brepose_ros.params import MatchParams
    from test_search import bracket_outline

    part = bracket_outline(0.5)
    scale, phi = 0.6, np.radians(30.0)  # view metres -> normalised image
    turn = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    image = CAMERA.focal * scale * part @ turn.T + [CAMERA.cx, CAMERA.cy]
    clutter = np.concatenate([square((560.0, 90.0), 50.0), square((80.0, 420.0), 40.0)])
    frame = frame_of(np.concatenate([image, clutter]))
    hypotheses = TetradHypotheses(one_view_graph(part), MatchParams())
    seed = Hypothesis(_seed_region(np.eye(3)), 0, 1.12 * scale, phi + np.radians(9.0), np.array([15.0, 0.0]) / 600.0,
                      0.0)
    matched = hypotheses.at_seeds([seed], frame, 1.2, MatchParams(), SERIAL)
    assert len(matched) == 1
    h = matched[0]
    assert h.scale == pytest.approx(scale, rel=0.01)
    assert np.degrees(abs(h.phi - phi)) < 0.5
    assert np.hypot(*h.shift) * CAMERA.focal < 1.0  # pixels
    assert h.coverage > 0.9
    # a seed whose window (108 px about (50, 30)) holds no segment gives nothing
    far = Hypothesis(_seed_region(np.eye(3)), 0, 0.3, phi, np.array([-0.45, -0.35]), 0.0)
    assert hypotheses.at_seeds([far], frame, 1.2, MatchParams(), SERIAL) == []


def test_seeds_matched_together_give_what_each_gives_alone_to_the_bit():
    """``at_seeds`` finds all seeds' windows as arrays and matches them in one compiled call
    per worker thread: each seed's hypothesis is still the one it gives alone, whatever the
    other seeds (among them one with no segment in its window and one whose window, the
    square, gives no similarity) and the threads."""
    from brepose_ros.camera import virtual_alignment
    from brepose_ros.online.hypotheses import Hypothesis, TetradHypotheses
    from brepose_ros.online.search import _seed_region
    from brepose_ros.online.workers import SERIAL, WorkerPool
    from test_search import bracket_outline

    part = bracket_outline(0.5)
    image = CAMERA.focal * 0.6 * part + [CAMERA.cx + 40.0, CAMERA.cy - 20.0]
    frame = frame_of(np.concatenate([image, square((560.0, 90.0), 50.0)]))
    hypotheses = TetradHypotheses(one_view_graph(part), MatchParams())
    off_axis = _seed_region(virtual_alignment(np.array([40.0, -20.0]) / CAMERA.focal))
    seeds = [Hypothesis(off_axis, 0, 0.62, 0.1, np.zeros(2), 0.0),
             Hypothesis(_seed_region(np.eye(3)), 0, 0.3, 0.0, np.array([-0.45, -0.35]), 0.0),  # an empty window
             Hypothesis(_seed_region(np.eye(3)), 0, 0.55, -0.15, np.array([0.07, -0.03]), 0.0),
             Hypothesis(_seed_region(np.eye(3)), 0, 0.2, 1.0, (np.array([560.0, 90.0]) - [CAMERA.cx, CAMERA.cy])
                        / CAMERA.focal, 0.0)]
    alone = [h for seed in seeds for h in hypotheses.at_seeds([seed], frame, 1.2, MatchParams(), SERIAL)]
    assert len(alone) == 2 and len(hypotheses._seed_jobs(seeds, frame, 1.2, MatchParams())) == 3
    pool = WorkerPool(2)
    try:
        together = hypotheses.at_seeds(seeds, frame, 1.2, MatchParams(), pool)
    finally:
        pool.close()
    assert len(together) == len(alone)
    assert [h.region.R_align is a.region.R_align for h, a in zip(together, alone)] == [True] * 2
    for h, a in zip(together, alone):
        assert (h.view, h.scale, h.phi, h.coverage, h.region.scale) == (a.view, a.scale, a.phi, a.coverage,
                                                                          a.region.scale)
        assert h.shift.tobytes() == a.shift.tobytes() and h.region.center.tobytes() == a.region.center.tobytes()


def test_the_virtual_alignment_is_the_rotation_between_the_axis_and_the_ray_to_the_bit():
    """``camera.virtual_alignment`` does ``geometry.rotation_between``'s steps on floats: the
    same matrix to the bit (signed zeros included) on the rays it sees."""
    from brepose_ros.camera import virtual_alignment
    from brepose_ros.geometry import rotation_between

    rng = np.random.default_rng(12)
    centers = np.concatenate([rng.normal(0.0, 0.4, (3000, 2)), [[0.0, 0.0], [-0.0, 0.0], [0.0, -0.0], [0.3, -0.0]]])
    for center in centers:
        want = rotation_between(np.array([0.0, 0.0, 1.0]), np.array([center[0], center[1], 1.0]))
        assert virtual_alignment(center).tobytes() == want.tobytes()

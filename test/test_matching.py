"""The metric space and the bipartite matcher on segment sets with exact answers."""
import numpy as np
import pytest

from brepose_ros import matching
from brepose_ros.metric_space import normalisation_of, tetrads, wrap_angle
from brepose_ros.params import MatchParams


def random_shape(rng, n=14):
    """A connected, irregular polyline plus a few chords: no symmetry to confuse rotation."""
    pts = rng.uniform(-1, 1, size=(n, 2)) * [1.0, 0.6]
    segs = np.stack([pts[:-1], pts[1:]], axis=1)
    return segs


def similarity(segs, scale, angle, shift):
    c, s = np.cos(angle), np.sin(angle)
    return scale * segs @ np.array([[c, s], [-s, c]]) + shift


def test_tetrads_of_known_segment():
    # horizontal segment y = 1 from x = 0 to 2: midpoint (1, 1), perpendicular foot (0, 1)
    (length, alpha, theta, r), = tetrads(np.array([[[0.0, 1.0], [2.0, 1.0]]]))
    assert length == pytest.approx(2.0)
    assert alpha == pytest.approx(np.pi / 4)
    assert theta == pytest.approx(np.pi / 2)
    assert r == pytest.approx(1.0)


def test_tetrads_turn_with_rotation_and_lengths_do_not():
    rng = np.random.default_rng(1)
    segs = random_shape(rng)
    turned = similarity(segs, 1.0, 0.7, 0.0)
    a, b = tetrads(segs), tetrads(turned)
    assert np.allclose(a[:, [0, 3]], b[:, [0, 3]])
    assert np.allclose(wrap_angle(b[:, 1] - a[:, 1]), 0.7)
    assert np.allclose(wrap_angle(b[:, 2] - a[:, 2]), 0.7)


def test_normalisation_removes_translation_and_scale():
    rng = np.random.default_rng(2)
    segs = random_shape(rng)
    moved = similarity(segs, 37.0, 0.0, np.array([300.0, -20.0]))
    a = normalisation_of(segs).apply(segs)
    b = normalisation_of(moved).apply(moved)
    assert np.allclose(a, b)


def test_rotation_candidates_contain_true_rotation():
    rng = np.random.default_rng(3)
    segs = random_shape(rng)
    for angle in (0.3, 2.0, 4.0):
        model = matching.describe(segs)
        image = matching.describe(similarity(segs, 1.0, angle, 0.0))
        phis = matching.rotation_candidates(model.orientation_histogram[None], image.orientation_histogram, 3)[0]
        assert np.min(np.abs(wrap_angle(phis - angle))) < np.radians(3)


def test_assignment_recovers_pairs_and_similarity_despite_clutter():
    rng = np.random.default_rng(4)
    segs = random_shape(rng, 16)
    order = rng.permutation(len(segs))
    image = similarity(segs[order], 1.0, 1.1, 0.0) + rng.normal(0, 0.01, size=(len(segs), 2, 2))
    clutter = rng.uniform(-2, 2, size=(6, 2, 2))
    image_all = np.concatenate([image, clutter])
    p = MatchParams()
    model_f, image_f = matching.describe(segs), matching.describe(image_all)
    assignment = matching.assign(model_f, image_f, 1.1, p)
    found = dict(zip(assignment.model_index, assignment.image_index))
    correct = sum(found.get(order[i]) == i for i in range(len(segs)))
    assert correct >= len(segs) - 2
    assert assignment.error_ratio < 0.3
    scale, angle, shift = matching.similarity_from_pairs(model_f, image_f, assignment, 1.1)
    assert scale == pytest.approx(1.0, abs=0.05)
    assert wrap_angle(angle - 1.1) == pytest.approx(0.0, abs=0.03)
    assert np.linalg.norm(shift) < 0.05


def test_wrong_rotation_costs_more_than_right_one():
    rng = np.random.default_rng(5)
    segs = random_shape(rng)
    model_f = matching.describe(segs)
    image_f = matching.describe(similarity(segs, 1.0, 0.5, 0.0))
    p = MatchParams()
    right = matching.assign(model_f, image_f, 0.5, p)
    wrong = matching.assign(model_f, image_f, 0.5 + np.pi / 2, p)
    assert right.cost < 0.5 * wrong.cost
    assert right.error_ratio < wrong.error_ratio


def test_weighted_similarity_is_exact_on_clean_points():
    rng = np.random.default_rng(6)
    src = rng.normal(size=(10, 2))
    dst = similarity(src[:, None, :], 2.5, -0.4, np.array([1.0, 2.0]))[:, 0]
    scale, angle, shift = matching.weighted_similarity(src, dst, np.ones(10))
    assert scale == pytest.approx(2.5)
    assert angle == pytest.approx(-0.4)
    assert np.allclose(shift, [1.0, 2.0])


def reference_coverage(source, target, tolerance, max_angle_deg=12.0, per_segment=4):
    """coverage written point by point."""
    covered = total = 0.0
    for a, b in source:
        for k in range(per_segment):
            point = a + (k + 0.5) / per_segment * (b - a)
            best = np.inf
            for c, d in target:
                cos = abs((b - a) @ (d - c)) / max(np.linalg.norm(b - a) * np.linalg.norm(d - c), 1e-18)
                u = np.clip((point - c) @ (d - c) / max((d - c) @ (d - c), 1e-18), 0.0, 1.0)
                if cos > np.cos(np.radians(max_angle_deg)):
                    best = min(best, np.linalg.norm(point - (c + u * (d - c))))
            total += np.linalg.norm(b - a) / per_segment
            covered += np.linalg.norm(b - a) / per_segment if best < tolerance else 0.0
    return covered / total


def test_coverage_matches_the_pointwise_definition():
    rng = np.random.default_rng(7)
    segs = random_shape(rng, 20)
    image = np.concatenate([similarity(segs[:14], 1.0, 0.02, 0.01), rng.uniform(-1, 1, size=(8, 2, 2))])
    for source, target in ((segs, image), (image, segs)):
        for tolerance in (0.01, 0.04, 0.1):
            assert matching.coverage(source, target, tolerance) == pytest.approx(
                reference_coverage(source, target, tolerance), abs=1e-12)


def test_prefilter_scores_match_a_plain_gather():
    rng = np.random.default_rng(8)
    views = [matching.describe(random_shape(rng, 10) * 1.5) for _ in range(20)]
    prefilter = matching.ChamferPrefilter(views)
    region = matching.describe(random_shape(rng, 12) * 1.5)
    maps = prefilter.distance_maps(region)
    phis = matching.rotation_candidates(np.stack([v.orientation_histogram for v in views]),
                                        region.orientation_histogram, 2)
    f = matching.ChamferPrefilter
    c, s = np.cos(phis.astype(np.float32))[..., None], np.sin(phis.astype(np.float32))[..., None]
    x, y = prefilter.points[:, None, :, 0], prefilter.points[:, None, :, 1]
    xr, yr = c * x - s * y, s * x + c * y
    cell = 2.0 * f.EXTENT / f.GRID
    col = np.clip(((xr + f.EXTENT) / cell).astype(int), 0, f.GRID - 1)
    row = np.clip(((yr + f.EXTENT) / cell).astype(int), 0, f.GRID - 1)
    ori = np.mod(prefilter.orientations[:, None, :] + phis.astype(np.float32)[..., None], np.pi)
    b = (ori / np.pi * f.ORIENT_BINS).astype(int) % f.ORIENT_BINS
    outside = (np.abs(xr) > f.EXTENT) | (np.abs(yr) > f.EXTENT)
    want = np.where(outside, f.TRUNCATE, maps[b, row, col]).mean(axis=2)
    assert np.array_equal(prefilter.scores(maps, phis), want)
    # any angle, not only those in [0, 2 pi) that rotation_candidates gives
    assert np.allclose(prefilter.scores(maps, phis - 4 * np.pi), want, atol=1e-6)

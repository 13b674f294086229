"""The metric space and the bipartite matcher on segment sets with exact answers."""
import numpy as np
import pytest

from brepose_ros.online import matching, prefilter
from brepose_ros.metric_space import normalisation_of, outline_normalisation
from brepose_ros.params import MatchParams


def random_shape(rng, n=14):
    """A connected, irregular polyline plus a few chords: no symmetry to confuse rotation."""
    pts = rng.uniform(-1, 1, size=(n, 2)) * [1.0, 0.6]
    segs = np.stack([pts[:-1], pts[1:]], axis=1)
    return segs


def similarity(segs, scale, angle, shift):
    c, s = np.cos(angle), np.sin(angle)
    return scale * segs @ np.array([[c, s], [-s, c]]) + shift


def wrapped(angle, period=2 * np.pi):
    """Angles as differences on the circle, in [-period / 2, period / 2)."""
    return (np.asarray(angle) + period / 2) % period - period / 2


def test_features_of_a_known_segment():
    # horizontal segment y = 1 from x = 2 to 0: midpoint (1, 1), perpendicular foot (0, 1)
    features = matching.describe(np.array([[[2.0, 1.0], [0.0, 1.0]]]))
    assert features.lengths[0] == pytest.approx(2.0)
    assert np.allclose(features.midpoints[0], [1.0, 1.0])
    assert features.orientations[0] == pytest.approx(0.0)  # a direction modulo pi
    assert np.allclose(features.feet[0], [0.0, 1.0])


def test_features_turn_with_rotation_and_lengths_do_not():
    """The tetrad's invariance the rotation search relies on (metric_space)."""
    rng = np.random.default_rng(1)
    segs = random_shape(rng)
    a, b = matching.describe(segs), matching.describe(similarity(segs, 1.0, 0.7, 0.0))
    turn = np.array([[np.cos(0.7), -np.sin(0.7)], [np.sin(0.7), np.cos(0.7)]])
    assert np.allclose(a.lengths, b.lengths)
    assert np.allclose(a.midpoints @ turn.T, b.midpoints) and np.allclose(a.feet @ turn.T, b.feet)
    assert np.allclose(wrapped(b.orientations - a.orientations, np.pi), 0.7)


def test_normalisation_removes_translation_and_scale():
    rng = np.random.default_rng(2)
    segs = random_shape(rng)
    moved = similarity(segs, 37.0, 0.0, np.array([300.0, -20.0]))
    a = normalisation_of(segs).apply(segs)
    b = normalisation_of(moved).apply(moved)
    assert np.allclose(a, b)


def test_outline_normalisation_is_the_hull_centroid_and_square_root_of_its_area():
    # a right triangle with legs 3 and 4 at (1, 2), and a segment inside it
    triangle = np.array([[[1.0, 2.0], [4.0, 2.0]], [[4.0, 2.0], [1.0, 6.0]], [[1.0, 6.0], [1.0, 2.0]],
                         [[1.5, 2.5], [2.0, 3.0]]])
    norm = outline_normalisation(triangle)
    assert norm.scale == pytest.approx(np.sqrt(6.0))
    assert np.allclose(norm.center, [2.0, 2.0 + 4.0 / 3.0])
    # points on one line have no area: the length-weighted normalisation stands in
    line = np.array([[[0.0, 0.0], [2.0, 0.0]], [[3.0, 0.0], [4.0, 0.0]]])
    fallback = outline_normalisation(line)
    length_weighted = normalisation_of(line)
    assert fallback.scale == length_weighted.scale and np.array_equal(fallback.center, length_weighted.center)


def segments_at(bins, length=1.0):
    """Segments of the given length lying at the centres of these orientation bins."""
    angles = (np.asarray(bins) + 0.5) * np.pi / prefilter.ORIENTATION_BINS
    ends = length * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    return np.stack([np.zeros_like(ends), ends], axis=1)


def test_rotation_candidates_tolerate_edges_a_bin_off():
    """The image's edges lie one bin (2.5 degrees) off the view's, one each way: only the
    smoothed histograms still correlate best at the true rotation, 0."""
    view, image = matching.describe(segments_at([10, 40])), matching.describe(segments_at([11, 39]))
    spectra = prefilter.orientation_spectra(histogram(view)[None])
    assert prefilter.rotation_candidates(spectra, histogram(image), 1)[0].tolist() == [0.0, np.pi]


def histogram(features):
    return prefilter.orientation_histogram(features.orientations, features.lengths)


def test_rotation_candidates_contain_true_rotation():
    rng = np.random.default_rng(3)
    segs = random_shape(rng)
    for angle in (0.3, 2.0, 4.0):
        model = matching.describe(segs)
        image = matching.describe(similarity(segs, 1.0, angle, 0.0))
        spectra = prefilter.orientation_spectra(histogram(model)[None])
        phis = prefilter.rotation_candidates(spectra, histogram(image), 3)[0]
        assert np.min(np.abs(wrapped(phis - angle))) < np.radians(3)


def batch(*sets, size=None):
    """The segment sets as one padded batch (to ``size``, or to the largest set plus 3)."""
    return matching.SegmentBatch.pad(list(sets), size or max(len(s) for s in sets) + 3)


def test_assignment_recovers_pairs_and_similarity_despite_clutter():
    rng = np.random.default_rng(4)
    segs = random_shape(rng, 16)
    order = rng.permutation(len(segs))
    image = similarity(segs[order], 1.0, 1.1, 0.0) + rng.normal(0, 0.01, size=(len(segs), 2, 2))
    clutter = rng.uniform(-2, 2, size=(6, 2, 2))
    image_f = matching.describe(np.concatenate([image, clutter]))
    model = batch(segs)
    phi = np.array([1.1])
    assignment = matching.assign(model, image_f, phi, MatchParams())
    found = assignment.image_index[0]
    correct = sum(found[order[i]] == i for i in range(len(segs)))
    assert correct >= len(segs) - 2
    assert assignment.nearest[0].sum() > 0.7 * len(segs)
    fit = matching.similarity_from_pairs(model, image_f, assignment, phi)
    assert fit.found[0]
    assert fit.scale[0] == pytest.approx(1.0, abs=0.05)
    assert wrapped(fit.angle[0] - 1.1) == pytest.approx(0.0, abs=0.03)
    assert np.linalg.norm(fit.shift[0]) < 0.05


def test_wrong_rotation_costs_more_than_right_one():
    rng = np.random.default_rng(5)
    segs = random_shape(rng)
    image_f = matching.describe(similarity(segs, 1.0, 0.5, 0.0))
    result = matching.assign(batch(segs, segs), image_f, np.array([0.5, 0.5 + np.pi / 2]), MatchParams())
    assert result.cost[0] < 0.5 * result.cost[1]
    assert result.nearest[0].sum() > result.nearest[1].sum()


def reference_distance_matrix(model, image, phi, p):
    """distance_matrix of one set, as it was written before batching."""
    c, s = np.cos(phi), np.sin(phi)
    rot = np.array([[c, -s], [s, c]])
    d_len = model.lengths[:, None] - image.lengths[None, :]
    d_mid = (model.midpoints @ rot.T)[:, None, :] - image.midpoints[None, :, :]
    d_feet = (model.feet @ rot.T)[:, None, :] - image.feet[None, :, :]
    d_ori = np.mod(model.orientations[:, None] + phi - image.orientations[None, :] + np.pi / 2, np.pi) - np.pi / 2
    return np.sqrt(p.weight_length * d_len**2
                   + p.weight_midpoint * np.einsum("ijk,ijk->ij", d_mid, d_mid)
                   + p.weight_orientation * d_ori**2
                   + p.weight_perpendicular * np.einsum("ijk,ijk->ij", d_feet, d_feet))


def test_batched_distances_are_the_per_set_distances_to_the_bit():
    rng = np.random.default_rng(9)
    sets = [random_shape(rng, n) for n in (5, 9, 14, 14)]
    image = matching.describe(random_shape(rng, 11))
    phis = np.array([0.0, 1.3, np.pi, 2 * np.pi - 1e-12])
    p = MatchParams()
    dist = matching.distance_matrix(batch(*sets), image, phis, p)
    for j, segs in enumerate(sets):
        want = reference_distance_matrix(matching.describe(segs), image, phis[j], p)
        assert np.array_equal(dist[j, :len(segs)], want)


def test_mod_pi_is_np_mod_to_the_bit():
    rng = np.random.default_rng(10)
    near_multiples = np.array([np.nextafter(k * np.pi, side) for k in range(-1, 5) for side in (-np.inf, np.inf)]
                              + [k * np.pi for k in range(-1, 4)] + [0.0, -0.0])
    x = np.concatenate([near_multiples[(near_multiples >= -np.pi) & (near_multiples < 4 * np.pi)],
                        rng.uniform(-np.pi, 4 * np.pi, 200_000)])
    assert np.array_equal(matching._mod_pi(x), np.mod(x, np.pi))
    outside = np.array([-4.0, 13.0, 100.0])
    assert np.array_equal(matching._mod_pi(outside), np.mod(outside, np.pi))


def test_padding_changes_no_assignment():
    """Padded segments never match and never set the empty distance, whose matrix maximum
    is over the set's real entries: a set gives the same pairs alone and in a batch."""
    rng = np.random.default_rng(11)
    sets = [random_shape(rng, n) * 0.2 for n in (4, 12, 7)]  # small sets: padding lies far
    image = matching.describe(np.concatenate([random_shape(rng, 10), [[[-3.0, -3.0], [3.0, 3.0]]]]))
    phis = np.array([0.2, 2.0, 4.0])
    p = MatchParams()
    together = matching.assign(batch(*sets, size=20), image, phis, p)
    for j, segs in enumerate(sets):
        alone = matching.assign(batch(segs, size=len(segs)), image, phis[j:j + 1], p)
        n = len(segs)
        assert np.array_equal(together.image_index[j, :n], alone.image_index[0])
        assert np.all(together.image_index[j, n:] == -1)
        assert np.array_equal(together.nearest[j, :n], alone.nearest[0]) and not together.nearest[j, n:].any()
        assert together.empty_distance[j] == alone.empty_distance[0]
        assert together.cost[j] == pytest.approx(alone.cost[0], rel=1e-15)


def test_weighted_similarity_is_exact_on_clean_points():
    rng = np.random.default_rng(6)
    src = rng.normal(size=(2, 10, 2))
    src[1] = 1.0  # no spread: no similarity
    dst = similarity(src[0][:, None, :], 2.5, -0.4, np.array([1.0, 2.0]))[:, 0]
    fit = matching.weighted_similarity(src, np.stack([dst, dst]), np.ones((2, 10)))
    assert fit.found.tolist() == [True, False]
    assert fit.scale[0] == pytest.approx(2.5)
    assert fit.angle[0] == pytest.approx(-0.4)
    assert np.allclose(fit.shift[0], [1.0, 2.0])


def reference_coverage(source, target, tolerance, max_angle_deg=12.0, per_segment=4):
    """One direction of coverage written point by point (each point against every target
    segment at once)."""
    c, d = target[:, 0], target[:, 1]
    covered = total = 0.0
    for a, b in source:
        cos = np.abs((d - c) @ (b - a)) / np.maximum(np.linalg.norm(b - a) * np.linalg.norm(d - c, axis=1), 1e-18)
        for k in range(per_segment):
            point = a + (k + 0.5) / per_segment * (b - a)
            u = np.clip(np.sum((point - c) * (d - c), axis=1) / np.maximum(np.sum((d - c) ** 2, axis=1), 1e-18), 0, 1)
            distance = np.linalg.norm(point - (c + u[:, None] * (d - c)), axis=1)
            near = np.any((cos > np.cos(np.radians(max_angle_deg))) & (distance < tolerance))
            total += np.linalg.norm(b - a) / per_segment
            covered += np.linalg.norm(b - a) / per_segment if near else 0.0
    return covered / total


def test_coverage_matches_the_pointwise_definition():
    rng = np.random.default_rng(7)
    segs = random_shape(rng, 20)
    sets = [segs, segs[5:12], similarity(segs, 1.0, 0.05, 0.03)]
    model = batch(*sets)
    for tolerance in (0.01, 0.04, 0.1):
        # some image segments just within and just beyond the tolerance
        image = np.concatenate([similarity(segs[:14], 1.0, 0.02, 0.01), segs[14:17] + 0.9 * tolerance / np.sqrt(2),
                                segs[17:] + 1.1 * tolerance, rng.uniform(-1, 1, size=(8, 2, 2))])
        model_share, image_share = matching.coverage(model.segments, model.valid, image, tolerance)
        for j, source in enumerate(sets):
            assert model_share[j] == pytest.approx(reference_coverage(source, image, tolerance), abs=1e-12)
            assert image_share[j] == pytest.approx(reference_coverage(image, source, tolerance), abs=1e-12)


def test_least_squares_is_lstsq_also_where_the_normal_equations_fail():
    rng = np.random.default_rng(12)
    rows, rhs = rng.normal(size=(3, 12, 4)), rng.normal(size=(3, 12))
    rows[1, :, 2:] = [0.6, 0.8]  # every point on one line: rank 3, lstsq's minimum-norm answer
    rows[2, 8:], rhs[2, 8:] = 0.0, 0.0  # four padding rows
    used = np.ones((3, 12), bool)
    used[2, 8:] = False
    got = matching._least_squares(rows, rhs, used)
    for j in range(3):
        want = np.linalg.lstsq(rows[j, used[j]], rhs[j, used[j]], rcond=None)[0]
        assert np.allclose(got[j], want, rtol=1e-12, atol=1e-12)


def test_align_to_lines_pulls_each_set_onto_the_image():
    rng = np.random.default_rng(13)
    image = random_shape(rng, 16)
    sets = [similarity(image, 1.02, 0.015, np.array([0.01, -0.02])), similarity(image[3:12], 0.98, -0.01, 0.015),
            image[:2]]  # too few segments to align: left alone
    model = batch(*sets)
    moved, total = matching.align_to_lines(model.segments, model.valid, image, (0.12, 0.04))
    for j in range(2):
        n = len(sets[j])
        assert np.abs(moved[j, :n] - image[3 * j:3 * j + n]).max() < 1e-9
        assert np.allclose(sets[j] @ total[j, :, :2].T + total[j, :, 2], moved[j, :n])
        alone, _ = matching.align_to_lines(model.segments[j:j + 1], model.valid[j:j + 1], image, (0.12, 0.04))
        assert np.allclose(alone[0], moved[j], rtol=0, atol=1e-14)
    assert np.array_equal(moved[2], model.segments[2]) and np.array_equal(total[2], np.eye(2, 3))


def test_prefilter_scores_match_a_plain_gather():
    """The compiled score equals numpy's gather and mean to the bit, on every point or every
    4th, whether the mean divides by a power of two or not."""
    rng = np.random.default_rng(8)
    views = [matching.describe(random_shape(rng, 10) * 1.5) for _ in range(20)]
    region = matching.describe(random_shape(rng, 12) * 1.5)
    spectra = prefilter.orientation_spectra(np.stack([histogram(v) for v in views]))
    phis = prefilter.rotation_candidates(spectra, histogram(region), 2)
    f = prefilter.ChamferPrefilter
    maps = f.distance_maps(*prefilter.spread_points(region.segments, 2000))
    for points_per_view, stride in ((32, 1), (32, 4), (30, 1), (30, 4)):
        chamfer = prefilter.ChamferPrefilter([v.segments for v in views], points_per_view)
        c, s = np.cos(phis.astype(np.float32))[..., None], np.sin(phis.astype(np.float32))[..., None]
        x, y = chamfer.points[:, None, ::stride, 0], chamfer.points[:, None, ::stride, 1]
        xr, yr = c * x - s * y, s * x + c * y
        cell = 2.0 * f.EXTENT / f.GRID
        col = np.clip(((xr + f.EXTENT) / cell).astype(int), 0, f.GRID - 1)
        row = np.clip(((yr + f.EXTENT) / cell).astype(int), 0, f.GRID - 1)
        ori = np.mod(chamfer.orientations[:, None, ::stride] + phis.astype(np.float32)[..., None], np.pi)
        b = (ori / np.pi * f.ORIENT_BINS).astype(int) % f.ORIENT_BINS
        outside = (np.abs(xr) > f.EXTENT) | (np.abs(yr) > f.EXTENT)
        want = np.where(outside, f.TRUNCATE, maps[b, row, col]).mean(axis=2)
        assert np.array_equal(chamfer.scores(maps, phis, stride), want)
        # any angle, not only those in [0, 2 pi) that rotation_candidates gives
        assert np.allclose(chamfer.scores(maps, phis - 4 * np.pi, stride), want, atol=1e-6)


def test_prefilter_shortlist_keeps_the_best_pairs_of_the_full_score():
    """The coarse stage only narrows the field: among 400 views the region's own view comes
    first, and what is returned is the full score's best of the pairs kept."""
    rng = np.random.default_rng(12)
    shapes = [random_shape(rng, 10) * 1.5 for _ in range(400)]
    views = [matching.describe(s) for s in shapes]
    chamfer = prefilter.ChamferPrefilter([v.segments for v in views])
    region = matching.describe(similarity(shapes[123], 1.0, 0.7, np.zeros(2)))
    maps = chamfer.distance_maps(*prefilter.spread_points(region.segments, 2000))
    spectra = prefilter.orientation_spectra(np.stack([histogram(v) for v in views]))
    phis = prefilter.rotation_candidates(spectra, histogram(region), 2)
    full = chamfer.scores(maps, phis)
    views_kept, which = chamfer.shortlist(maps, phis, 5)
    assert len(views_kept) == 5 and views_kept[np.argmin(full[views_kept, which])] == 123
    assert full[123].min() == full.min()
    # with a coarse stage that keeps everything, the shortlist is the full score's best 5
    keep_all = prefilter.ChamferPrefilter([v.segments for v in views])
    keep_all.COARSE_KEEP = full.size
    v_all, w_all = keep_all.shortlist(maps, phis, 5)
    assert sorted(full[v_all, w_all]) == sorted(np.sort(full.ravel())[:5])


def test_prefilter_maps_keep_directions_apart_and_drop_points_outside():
    f = prefilter.ChamferPrefilter([random_shape(np.random.default_rng(1), 6)])
    cell = 2 * f.EXTENT / f.GRID

    def index(v):
        return int(np.floor((v + f.EXTENT) / cell))

    points = np.array([[0.0, 0.0], [0.5, -0.5], [9.0, 0.0]])  # the last lies outside the square
    maps = f.distance_maps(points, np.array([0.0, np.pi / 2, 0.0]))
    horizontal, vertical = maps[0], maps[f.ORIENT_BINS // 2]
    assert horizontal[index(0.0), index(0.0)] == 0 and vertical[index(-0.5), index(0.5)] == 0
    assert (horizontal == 0).sum() == 1 and (vertical == 0).sum() == 1
    # two cells away (OpenCV's 3x3 chamfer counts an axial step as 0.955 cells)
    assert horizontal[index(0.0), index(0.1)] == pytest.approx((index(0.1) - index(0.0)) * cell, rel=0.05)
    assert vertical[index(0.0), index(0.0)] == pytest.approx(f.TRUNCATE)  # 0.7 away, truncated
    assert np.all(maps[[1, 2, 4, 5]] == np.float32(f.TRUNCATE))

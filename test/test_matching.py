"""The metric space and the bipartite matcher on segment sets with exact answers."""
import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

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


def test_ranked_peaks_are_repeated_argmax_over_the_cyclic_peaks():
    """The compiled ranking gives what ``count`` rounds of np.argmax over the peaks did (each
    taken peak then -inf): plateaus and ties to the lower bin, bin 0 once the peaks run out."""
    rng = np.random.default_rng(13)
    corr = np.round(rng.normal(size=(400, 72)), 1)  # ties and plateaus
    corr[:3] = 0.0  # flat: every bin a peak
    corr[3] = np.arange(72.0)  # one peak, at the last bin (its right neighbour is bin 0)
    for count in (1, 3, 40):
        wrapped = np.concatenate([corr[:, -1:], corr, corr[:, :1]], axis=1)
        peaks = np.where((corr >= wrapped[:, :-2]) & (corr >= wrapped[:, 2:]), corr, -np.inf)
        want = np.empty((len(corr), count), np.int64)
        for k in range(count):
            want[:, k] = best = np.argmax(peaks, axis=1)
            peaks[np.arange(len(corr)), best] = -np.inf
        got = np.empty((len(corr), count), np.int64)
        prefilter.ranked_peaks(corr, count, got)
        assert np.array_equal(got, want)
    assert got[3, :3].tolist() == [71, 0, 0]


def test_rotation_candidates_contain_true_rotation():
    rng = np.random.default_rng(3)
    segs = random_shape(rng)
    for angle in (0.3, 2.0, 4.0):
        model = matching.describe(segs)
        image = matching.describe(similarity(segs, 1.0, angle, 0.0))
        spectra = prefilter.orientation_spectra(histogram(model)[None])
        phis = prefilter.rotation_candidates(spectra, histogram(image), 3)[0]
        assert np.min(np.abs(wrapped(phis - angle))) < np.radians(3)


WEIGHTS = np.array([MatchParams().weight_length, MatchParams().weight_midpoint, MatchParams().weight_orientation,
                    MatchParams().weight_perpendicular])


def assign(model, image, phi, p=MatchParams()):
    """(cost, image index per model segment, nearest) of one model set against an image set."""
    return matching._assignment(matching._geometry(model), matching._geometry(image), phi, WEIGHTS,
                                p.empty_coefficient, p.nearest_threshold)


def test_kuhn_munkres_is_scipys_assignment_ties_included():
    """The compiled Kuhn-Munkres follows SciPy's algorithm step for step: the same pairs on
    wide, tall and square matrices, also where many assignments cost the same."""
    rng = np.random.default_rng(14)
    for trial in range(600):
        shape = tuple(rng.integers(1, 30, size=2))
        cost = (rng.integers(0, 4, size=shape).astype(float) if trial % 3 == 0  # many ties
                else np.minimum(rng.uniform(size=shape), 0.3 if trial % 3 == 1 else 1.0))  # clipped, as assign does
        rows, cols = linear_sum_assignment(cost)
        want = np.full(shape[0], -1)
        want[rows] = cols
        assert np.array_equal(matching._kuhn_munkres(cost), want)


def test_assignment_recovers_pairs_and_similarity_despite_clutter():
    rng = np.random.default_rng(4)
    segs = random_shape(rng, 16)
    order = rng.permutation(len(segs))
    image = similarity(segs[order], 1.0, 1.1, 0.0) + rng.normal(0, 0.01, size=(len(segs), 2, 2))
    image = np.concatenate([image, rng.uniform(-2, 2, size=(6, 2, 2))])  # clutter
    _, found, nearest = assign(segs, image, 1.1)
    correct = sum(found[order[i]] == i for i in range(len(segs)))
    assert correct >= len(segs) - 2
    assert nearest.sum() > 0.7 * len(segs)
    lengths = matching._geometry(segs)[0], matching._geometry(image)[0]
    scale, angle, shift, ok = matching._similarity_from_pairs(segs, lengths[0], image, lengths[1], found, nearest, 1.1)
    assert ok
    assert scale == pytest.approx(1.0, abs=0.05)
    assert wrapped(angle - 1.1) == pytest.approx(0.0, abs=0.03)
    assert np.linalg.norm(shift) < 0.05


def test_wrong_rotation_costs_more_than_right_one():
    rng = np.random.default_rng(5)
    segs = random_shape(rng)
    image = similarity(segs, 1.0, 0.5, 0.0)
    right, wrong = assign(segs, image, 0.5), assign(segs, image, 0.5 + np.pi / 2)
    assert right[0] < 0.5 * wrong[0]
    assert right[2].sum() > wrong[2].sum()


def reference_distance_matrix(model, image, phi, p):
    """The tetrad distance written out with numpy, one set at a time."""
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


def test_distances_are_the_tetrad_distance_written_out():
    rng = np.random.default_rng(9)
    image = random_shape(rng, 11)
    for n, phi in ((5, 0.0), (9, 1.3), (14, np.pi), (14, 2 * np.pi - 1e-12)):
        segs = random_shape(rng, n)
        dist = matching._distances(matching._geometry(segs), matching._geometry(image), phi, WEIGHTS)
        want = reference_distance_matrix(matching.describe(segs), matching.describe(image), phi, MatchParams())
        assert np.allclose(dist, want, rtol=1e-13, atol=1e-13)


def test_mod_is_np_mod_to_the_bit():
    rng = np.random.default_rng(10)
    near_multiples = [np.nextafter(k * np.pi, side) for k in range(-1, 5) for side in (-np.inf, np.inf)]
    x = np.concatenate([near_multiples, [k * np.pi for k in range(-1, 4)], [0.0, -0.0, -4.0, 13.0, 100.0],
                        rng.uniform(-np.pi, 4 * np.pi, 5000)])
    got = np.array([matching._mod(v, np.pi) for v in x])
    assert np.array_equal(got, np.mod(x, np.pi)) and not np.signbit(got).any()


def test_a_job_aligns_alike_alone_and_among_others():
    """Jobs are independent: a job's similarity and coverage do not depend on the batch, nor
    on the regions of the batch's other jobs (the worker threads split the jobs anywhere, the
    search's seeds are a region each)."""
    rng = np.random.default_rng(11)
    views = [random_shape(rng, n) * 0.5 for n in (4, 12, 7, 12)]
    image = np.concatenate([similarity(views[1], 1.1, 0.4, np.array([0.05, 0.0])), random_shape(rng, 6) * 0.5])
    other = np.concatenate([similarity(views[2], 0.9, -1.0, np.array([0.0, 0.1])), random_shape(rng, 3) * 0.5])
    regions = np.concatenate([image, other])
    region_offsets = np.array([0, len(image), len(image) + len(other)])
    segments = np.concatenate(views)
    offsets = np.concatenate([[0], np.cumsum([len(v) for v in views])])
    jobs, phi = np.array([0, 1, 2, 2, 3, 1]), np.array([0.2, 0.4, 4.0, -1.0, 1.0, 0.4 + np.pi])
    of_region = np.array([0, 0, 0, 1, 0, 1])
    together = matching.align(segments, offsets, jobs, phi, regions, region_offsets, of_region, MatchParams())
    for j, scale, angle in ((1, 1.1, 0.4), (3, 0.9, -1.0)):  # the views the regions show, at their rotations
        assert j in together.jobs
        k = list(together.jobs).index(j)
        assert together.scale[k] == pytest.approx(scale, abs=1e-6)
        assert together.angle[k] == pytest.approx(angle, abs=1e-6)
        assert together.coverage[k] > 0.7
    for j in range(len(jobs)):
        own = (image, other)[of_region[j]]
        alone = matching.align(segments, offsets, jobs[j:j + 1], phi[j:j + 1], own, np.array([0, len(own)]),
                               np.zeros(1, np.int64), MatchParams())
        assert (j in together.jobs) == (len(alone.jobs) == 1)
        if j in together.jobs:
            k = list(together.jobs).index(j)
            got = [together.scale[k], together.angle[k], *together.shift[k], together.coverage[k]]
            assert np.array_equal(got, [alone.scale[0], alone.angle[0], *alone.shift[0], alone.coverage[0]])


def test_weighted_similarity_is_exact_on_clean_points():
    rng = np.random.default_rng(6)
    src = rng.normal(size=(10, 2))
    dst = similarity(src[:, None, :], 2.5, -0.4, np.array([1.0, 2.0]))[:, 0]
    scale, angle, shift, found = matching._weighted_similarity(src, dst, np.ones(10))
    assert found
    assert scale == pytest.approx(2.5)
    assert angle == pytest.approx(-0.4)
    assert np.allclose(shift, [1.0, 2.0])
    assert not matching._weighted_similarity(np.ones((10, 2)), dst, np.ones(10))[3]  # no spread: no similarity


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
    min_cos = np.cos(np.radians(matching.COVERAGE_MAX_ANGLE_DEG))
    for tolerance in (0.01, 0.04, 0.1):
        # some image segments just within and just beyond the tolerance
        image = np.concatenate([similarity(segs[:14], 1.0, 0.02, 0.01), segs[14:17] + 0.9 * tolerance / np.sqrt(2),
                                segs[17:] + 1.1 * tolerance, rng.uniform(-1, 1, size=(8, 2, 2))])
        for source in (segs, segs[5:12], similarity(segs, 1.0, 0.05, 0.03)):
            model_share, image_share = matching._coverage(source, image, tolerance, min_cos)
            assert model_share == pytest.approx(reference_coverage(source, image, tolerance), abs=1e-12)
            assert image_share == pytest.approx(reference_coverage(image, source, tolerance), abs=1e-12)


def test_least_squares_is_lstsq_also_where_the_normal_equations_fail():
    rng = np.random.default_rng(12)
    rows, rhs = rng.normal(size=(3, 12, 4)), rng.normal(size=(3, 12))
    rows[1, :, 2:] = [0.6, 0.8]  # every point on one line: rank 3, lstsq's minimum-norm answer
    rows[2, :, 3] = 1e-4 * rows[2, :, 0]  # condition number ~1e4
    for j in range(3):
        want = np.linalg.lstsq(rows[j], rhs[j], rcond=None)[0]
        assert np.allclose(matching._least_squares(rows[j], rhs[j]), want, rtol=1e-10, atol=1e-12)


def test_align_to_lines_pulls_a_set_onto_the_image():
    rng = np.random.default_rng(13)
    image = random_shape(rng, 16)
    cos10 = np.cos(np.radians(10.0))
    tolerances = np.array([0.12, 0.04])
    for start, model in ((0, similarity(image, 1.02, 0.015, np.array([0.01, -0.02]))),
                         (3, similarity(image[3:12], 0.98, -0.01, 0.015))):
        moved = model.copy()
        total = matching._align_to_lines(moved, image, tolerances, cos10)
        assert np.abs(moved - image[start:start + len(model)]).max() < 1e-9
        assert np.allclose(model @ total[:, :2].T + total[:, 2], moved)
    few = image[:2].copy()  # too few segments to align: left alone
    assert np.array_equal(matching._align_to_lines(few, image, tolerances, cos10), np.eye(2, 3))
    assert np.array_equal(few, image[:2])


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

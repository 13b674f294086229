"""Colour regions: the places of a colour image with the part's own surface colour, and the
model colour that a coloured mesh carries into its aspect graph."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from brepose_ros.aspect_graph import AspectGraph, AspectGraphError
from brepose_ros.chromaticity import BINS, surface_histogram
from brepose_ros.online.colour_regions import MARGIN_PIXELS, ONE_PLACE_SHARE, colour_places, colour_regions
from test_aspect_graph import rewritten
from graph_helpers import one_view_graph

#: BGR colours of the synthetic scene: the part's brown, two other objects, a beige desk
BROWN, BLUE, GREEN, DESK = (50, 60, 150), (160, 90, 40), (60, 150, 60), (150, 170, 185)


def model_histogram(colour=BROWN, seed=0) -> np.ndarray:
    """A scanned surface of one colour: 500 vertices of it, lit brighter and dimmer, with noise."""
    rng = np.random.default_rng(seed)
    light = rng.uniform(0.6, 1.3, (500, 1))
    colours = np.clip(np.array(colour) * light + rng.normal(0, 4, (500, 3)), 0, 255).astype(np.uint8)
    return surface_histogram(colours, rng.uniform(0.5, 1.5, 500))


def scene(seed=1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 480 x 640 photo-like image: a desk of noisy grain, a brown disc (the part, in shadow
    on its left), a blue and a green box; the disc's mask and the boxes' mask."""
    rng = np.random.default_rng(seed)
    image = np.array(DESK, np.float32) * rng.uniform(0.7, 1.1, (480, 640, 1))
    part, blue, green = (np.zeros((480, 640), np.uint8) for _ in range(3))
    cv2.circle(part, (200, 240), 45, 1, -1)
    cv2.rectangle(blue, (300, 200), (380, 300), 1, -1)
    cv2.rectangle(green, (420, 100), (520, 180), 1, -1)
    shade = 0.6 + 0.6 * np.nonzero(part)[1] / 640.0
    image[part > 0] = np.array(BROWN, np.float32) * shade[:, None]
    image[blue > 0], image[green > 0] = BLUE, GREEN
    image += rng.normal(0, 3, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8), part > 0, (blue > 0) | (green > 0)


def test_the_regions_hold_the_part_and_its_outline_and_drop_the_other_objects():
    image, part, others = scene()
    regions = colour_regions(image, model_histogram(), 0.5, 400)
    assert regions is not None and regions.dtype == bool
    outline = cv2.dilate(part.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0  # its edges, 2 px either side
    assert regions[outline].mean() == 1.0
    assert regions[others].mean() < 0.01
    assert regions.mean() < 2 * outline.mean()  # the desk is not the part's colour
    # grown by MARGIN_PIXELS, not more: nothing farther from the disc than that
    far = cv2.dilate(part.astype(np.uint8), np.ones((2 * MARGIN_PIXELS + 5,) * 2, np.uint8)) == 0
    assert not regions[far].any()


def test_the_places_of_the_regions_ranked_by_the_colour_they_hold():
    """The scene's brown disc and two smaller ones: the regions split into three places,
    ranked by the part's colour they hold (the largest disc first), at most ``count``; regions
    that are one place, or nearly all one, are no places to search again."""
    image, part, _ = scene()
    discs = [part]
    for centre, radius in (((520, 90), 30), ((480, 380), 38)):
        disc = cv2.circle(np.zeros((480, 640), np.uint8), centre, radius, 1, -1) > 0
        image[disc] = BROWN
        discs.append(disc)
    regions = colour_regions(image, model_histogram(), 0.5, 400)
    places = colour_places(image, model_histogram(), regions, 3)
    assert len(places) == 3
    for place, disc in zip(places, [discs[0], discs[2], discs[1]]):
        near = cv2.dilate(disc.astype(np.uint8), np.ones((2 * MARGIN_PIXELS + 3,) * 2, np.uint8)) > 0
        assert place[disc].all() and not (place & ~near).any()
    assert all(np.array_equal(a, b) for a, b in zip(colour_places(image, model_histogram(), regions, 2), places))
    assert len(colour_places(image, model_histogram(), regions, 2)) == 2
    assert colour_places(image, model_histogram(), regions, 0) == []
    one, _, _ = scene()
    assert colour_places(one, model_histogram(), colour_regions(one, model_histogram(), 0.5, 400), 3) == []
    # the first disc grown to nearly all the regions: they are one place (a grey part's desk)
    cv2.circle(image, (200, 240), 180, BROWN, -1)
    regions = colour_regions(image, model_histogram(), 0.5, 400)
    largest = regions & (cv2.circle(np.zeros((480, 640), np.uint8), (200, 240), 190, 1, -1) > 0)
    assert largest.sum() > ONE_PLACE_SHARE * regions.sum() and (regions & ~largest).any()
    assert colour_places(image, model_histogram(), regions, 3) == []


def test_no_regions_without_a_colour_to_look_for():
    image, _, _ = scene()
    assert colour_regions(image, None, 0.5, 400) is None  # a STEP part: no colour
    grey = cv2.cvtColor(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    assert colour_regions(grey, model_histogram(), 0.5, 400) is None  # a grey image in BGR
    assert colour_regions(image[:, :, 0], model_histogram(), 0.5, 400) is None
    # a part coloured as nothing in the image: rather the whole image than none of it
    assert colour_regions(image, model_histogram((200, 40, 200)), 0.5, 400) is None


def test_the_surface_histogram_weighs_colours_by_area():
    colours = np.array([BROWN, BLUE], np.uint8)
    histogram = surface_histogram(colours, np.array([3.0, 1.0]))
    assert histogram.shape == (BINS, BINS) and histogram.dtype == np.float32
    assert histogram.sum() == pytest.approx(1.0)
    brown = histogram[int((BROWN[2] + 1) / (sum(BROWN) + 3) * BINS), int((BROWN[1] + 1) / (sum(BROWN) + 3) * BINS)]
    blue = histogram[int((BLUE[2] + 1) / (sum(BLUE) + 3) * BINS), int((BLUE[1] + 1) / (sum(BLUE) + 3) * BINS)]
    assert brown == pytest.approx(3 * blue)


def test_a_graphs_colour_is_kept_by_the_file_and_checked_and_may_be_absent(tmp_path):
    plain = one_view_graph(np.array([[[0.0, 0.0], [0.1, 0.0]], [[0.1, 0.0], [0.1, 0.1]]]))
    loaded = AspectGraph.load(plain.save(tmp_path / "plain.brepose.npz"))
    assert loaded.colour_histogram is None and "colour_histogram" not in loaded.arrays()
    coloured = dataclasses.replace(plain, colour_histogram=model_histogram())
    path = coloured.save(tmp_path / "coloured.brepose.npz")
    assert np.array_equal(AspectGraph.load(path).colour_histogram, coloured.colour_histogram)
    with pytest.raises(AspectGraphError, match="colour_histogram is not a histogram"):
        AspectGraph.load(rewritten(colour_histogram=lambda a: -a)(path, tmp_path))
    with pytest.raises(AspectGraphError, match="array colour_histogram has dtype"):
        AspectGraph.load(rewritten(colour_histogram=lambda a: a[:-1])(coloured.save(path), tmp_path))


@pytest.fixture(scope="module")
def coloured_bracket(builtin_step):
    """The sharp bracket's graph at 12 degrees with a brown surface colour, and its mesh."""
    from brepose_ros.offline.cad import load_step, tessellate
    from brepose_ros.offline.compiler import compile_aspect_graph

    step = builtin_step("sharp_bracket")
    graph = compile_aspect_graph(step, step_deg=12.0, workers=2, progress=False)
    return dataclasses.replace(graph, colour_histogram=model_histogram()), tessellate(load_step(step))


def test_the_estimator_finds_the_part_of_its_colour_beside_a_twin_of_another(coloured_bracket):
    """Two brackets of the same shape on a desk, the part brown on the left, a blue twin
    larger and nearer on the right: within its colour regions the estimator sees the brown
    one's edges alone and finds it."""
    from brepose_ros.camera import Camera
    from brepose_ros.geometry import look_at_rotation, normalize
    from brepose_ros.online.estimator import Estimator
    from brepose_ros.synthetic.render import Material, Placed, render

    graph, mesh = coloured_bracket
    camera = Camera(600.0, 600.0, 320.0, 240.0, 640, 480)
    R = look_at_rotation(normalize(np.array([0.4, -0.6, -1.0])))
    part_t, twin_t = np.array([-0.09, 0.0, 0.55]), np.array([0.08, 0.01, 0.45])
    desk = np.array(DESK, np.float32) * np.random.default_rng(2).uniform(0.7, 1.1, (480, 640, 1))
    image = render(camera, [Placed(mesh, R, centre - R @ graph.model_center, Material(color=tuple(np.array(bgr) / 255)))
                            for centre, bgr in ((part_t, BROWN), (twin_t, BLUE))],
                   background=desk.astype(np.uint8), color=True).image
    estimator = Estimator(graph)
    try:
        frame = estimator.part_frame(image, camera)
        ys, xs = np.nonzero(frame.evidence.edges)
        part_x = camera.project(part_t[None])[0, 0]
        assert len(xs) > 100 and np.abs(xs - part_x).max() < 0.6 * camera.focal * graph.model_diameter / part_t[2]
        estimate = estimator.estimate(image, camera)
        centre = estimate.R @ graph.model_center + estimate.t
        assert np.linalg.norm(centre - part_t) < 0.1 * graph.model_diameter, (centre, part_t)
    finally:
        estimator.close()



def test_within_its_colour_regions_the_search_finds_a_part_smaller_than_the_default_sizes(coloured_bracket):
    """The brown bracket alone, about 100 px across where the search's default smallest size
    is 0.2 of the 800 px diagonal: its colour region sets the sizes searched, which then hold
    it, and the search's best place is the part's, at its size."""
    from brepose_ros.camera import Camera
    from brepose_ros.geometry import look_at_rotation, normalize
    from brepose_ros.online.estimator import Estimator
    from brepose_ros.online.search import TemplateSearch
    from brepose_ros.params import SearchParams
    from brepose_ros.synthetic.render import Material, Placed, render

    graph, mesh = coloured_bracket
    camera = Camera(600.0, 600.0, 320.0, 240.0, 640, 480)
    R = look_at_rotation(normalize(np.array([0.4, -0.6, -1.0])))
    size = 100.0  # the part's diameter, pixels
    part_t = np.array([0.03, -0.02, camera.focal * graph.model_diameter / size])
    desk = np.array(DESK, np.float32) * np.random.default_rng(3).uniform(0.7, 1.1, (480, 640, 1))
    brown = Material(color=tuple(np.array(BROWN) / 255))
    image = render(camera, [Placed(mesh, R, part_t - R @ graph.model_center, brown)],
                   background=desk.astype(np.uint8), color=True).image
    estimator = Estimator(graph)
    try:
        frame = estimator.part_frame(image, camera)
    finally:
        estimator.close()
    p = SearchParams()
    search = TemplateSearch(graph, p)
    assert frame.region_extents is not None
    whole = search.sizes(dataclasses.replace(frame, region_extents=None), p)
    assert whole[0] > 1.5 * size
    # a region as large as the image (a grey part on a grey desk) bounds nothing
    assert np.array_equal(search.sizes(dataclasses.replace(frame, region_extents=np.array([800.0])), p), whole)
    sizes = search.sizes(frame, p)
    assert sizes[0] <= size <= sizes[-1] and sizes[-1] < p.max_size_fraction * np.hypot(640, 480)
    (centre, found), = search.places(search.coarse(frame, p), 1)
    assert np.hypot(*(centre - camera.project(part_t[None])[0])) < 0.25 * size, centre  # within the part
    assert size / 1.3 < found < 1.3 * size, found


def test_the_estimate_within_each_colour_place_never_scores_below_the_whole_regions(coloured_bracket, monkeypatch):
    """The brown bracket and a brown box of like size beside it: the regions split into two
    places, the estimate is made again within each (``edges.colour_places``), and the pose
    kept scores at least the whole regions' one on the whole regions' edges and is the
    bracket's; with ``colour_places`` 0 no place is estimated."""
    from brepose_ros.camera import Camera
    from brepose_ros.geometry import look_at_rotation, normalize
    from brepose_ros.online import estimator as estimator_module
    from brepose_ros.online.estimator import Estimator
    from brepose_ros.params import EstimatorParams
    from brepose_ros.synthetic.render import Material, Placed, render

    graph, mesh = coloured_bracket
    camera = Camera(600.0, 600.0, 320.0, 240.0, 640, 480)
    R = look_at_rotation(normalize(np.array([0.4, -0.6, -1.0])))
    part_t = np.array([-0.08, 0.0, 0.55])
    desk = np.array(DESK, np.float32) * np.random.default_rng(4).uniform(0.7, 1.1, (480, 640, 1))
    desk[180:260, 430:530] = np.array(BROWN, np.float32) * 0.9  # a brown box of like size
    brown = Material(color=tuple(np.array(BROWN) / 255))
    image = render(camera, [Placed(mesh, R, part_t - R @ graph.model_center, brown)], background=desk.astype(np.uint8),
                   color=True).image
    counted = []

    def places(*args):
        counted.append(colour_places(*args))
        return counted[-1]

    monkeypatch.setattr(estimator_module, "colour_places", places)
    scores = {}
    for count in (0, 3):
        estimator = Estimator(graph, EstimatorParams().with_flat({"edges.colour_places": count}))
        try:
            estimate = estimator.estimate(image, camera)
        finally:
            estimator.close()
        centre = estimate.R @ graph.model_center + estimate.t
        assert np.linalg.norm(centre - part_t) < 0.1 * graph.model_diameter, (count, centre, part_t)
        scores[count] = estimate.score
    assert [len(c) for c in counted] == [0, 2]
    assert scores[3] >= scores[0]

"""Visible edges of meshes with known answers, mesh aspect graphs in the checked file
format, and the estimator on them: a rendered mesh and one real LM-O photograph."""
from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from brepose_ros.aspect_graph import AspectGraph, AspectGraphError
from brepose_ros.camera import Camera
from brepose_ros.geometry import look_at_rotation, normalize, rotation_angle_deg
from brepose_ros.offline.cad import Mesh, load_step, tessellate
from brepose_ros.offline.compiler import compile_aspect_graph
from brepose_ros.offline.hidden_lines import OUTLINE, SHARP, view_coordinates
from brepose_ros.offline.mesh import load_mesh
from brepose_ros.offline.mesh_lines import MeshLineRemover
from brepose_ros.online.colour_regions import colour_regions
from brepose_ros.online.estimator import Estimator
from brepose_ros.online.image_edges import detect_edges
from brepose_ros.online.scoring import EdgeEvidence
from brepose_ros.params import EdgeParams
from brepose_ros.synthetic.render import Placed, render

trimesh = pytest.importorskip("trimesh")  # the [compile] extra
pytestmark = pytest.mark.cad

HALF = 0.025  # the test cube is 50 mm, centred on the origin
CORNERS = np.array([[x, y, z] for x in (-HALF, HALF) for y in (-HALF, HALF) for z in (-HALF, HALF)])


@pytest.fixture(scope="module")
def cube_ply(tmp_path_factory):
    """A 50 mm cube of 768 triangles (each face a 8 x 8 grid of squares)."""
    path = tmp_path_factory.mktemp("meshes") / "cube.ply"
    trimesh.creation.box((2 * HALF,) * 3).subdivide().subdivide().subdivide().export(str(path))
    return path


@pytest.fixture(scope="module")
def noisy_cube_ply(tmp_path_factory):
    """The cube with every vertex moved at random by 0.1 mm (sigma), as a scan would be."""
    mesh = trimesh.creation.box((2 * HALF,) * 3).subdivide().subdivide().subdivide()
    mesh.vertices += np.random.default_rng(0).normal(0.0, 1e-4, mesh.vertices.shape)
    path = tmp_path_factory.mktemp("meshes") / "noisy_cube.ply"
    mesh.export(str(path))
    return path


def visible(path, direction, units="m"):
    part = load_mesh(path, units)
    rotation = look_at_rotation(normalize(np.asarray(direction, dtype=float)))
    return part, rotation, MeshLineRemover(part).segments(rotation)


@pytest.mark.parametrize("direction, count", [((0, 0, -1), 4), ((1, 1, 1), 9), ((0.2, 0.3, -1), 9)],
                         ids=["face-on", "body-diagonal", "oblique"])
def test_cube_mesh_shows_its_visible_creases_once(cube_ply, direction, count):
    part, rotation, view = visible(cube_ply, direction)
    assert len(view.kinds) == count and np.all(view.kinds == SHARP)
    distance, _ = cKDTree(CORNERS).query(view.segments_3d.reshape(-1, 3))
    assert distance.max() < 1e-9  # every section runs corner to corner


def test_cube_mesh_has_twelve_crease_edges(cube_ply):
    """Over views from every side, the distinct visible sections are the cube's 12 edges."""
    part = load_mesh(cube_ply, "m")
    remover = MeshLineRemover(part)
    edges = set()
    for direction in [(1, 1, 1), (-1, -1, -1), (1, -1, 0.5), (-1, 1, -0.5)]:
        view = remover.segments(look_at_rotation(normalize(np.array(direction, dtype=float))))
        ends = cKDTree(CORNERS).query(view.segments_3d.reshape(-1, 3))[1].reshape(-1, 2)
        edges |= {tuple(sorted(pair)) for pair in ends.tolist()}
    assert len(edges) == 12
    assert all(np.sum(CORNERS[a] != CORNERS[b]) == 1 for a, b in edges)  # along one axis each


@pytest.mark.parametrize("direction", [(1, 1, 1), (0.2, 0.3, -1), (-0.6, 1, 0.3)])
def test_noisy_cube_mesh_still_shows_its_edges(noisy_cube_ply, direction):
    part, rotation, view = visible(noisy_cube_ply, direction)
    assert len(view.kinds) == 9 and np.all(view.kinds == SHARP)
    distance, _ = cKDTree(CORNERS).query(view.segments_3d.reshape(-1, 3))
    assert distance.max() < 1e-3  # within a few noise sigmas of the true corners


@pytest.fixture(scope="module")
def cylinder_stl(tmp_path_factory):
    """r 20 mm, h 50 mm, 64 facets, stored in millimetres."""
    path = tmp_path_factory.mktemp("meshes") / "cylinder.stl"
    trimesh.creation.cylinder(radius=20.0, height=50.0, sections=64).export(str(path))
    return path


def test_cylinder_mesh_side_on_shows_two_outlines_and_its_two_end_circles(cylinder_stl):
    part, rotation, view = visible(cylinder_stl, (1, 0, 0), units="mm")
    assert sorted(view.kinds.tolist()) == [SHARP, SHARP, OUTLINE, OUTLINE]
    xy = view_coordinates(view.segments_3d, rotation, part.center)
    outline = xy[view.kinds == OUTLINE]
    assert np.allclose(np.abs(outline[..., 0]), 0.020, atol=1e-4)  # x = +-r, the silhouettes
    assert np.allclose(np.ptp(outline[..., 1], axis=1), 0.050, atol=1e-4)
    circles = xy[view.kinds == SHARP]
    assert np.allclose(np.abs(circles[..., 1]), 0.025, atol=1e-6)  # the end circles seen edge-on
    assert np.allclose(np.ptp(circles[..., 0], axis=1), 0.040, atol=2e-4)


def test_cylinder_mesh_seen_obliquely_shows_its_near_circle_whole(cylinder_stl):
    part, rotation, view = visible(cylinder_stl, (1, 0, 0.6), units="mm")  # seen from below
    ends = view.segments_3d[view.kinds == SHARP]
    assert np.allclose(np.linalg.norm(ends[..., :2], axis=2), 0.020, atol=1e-3 * part.diameter)
    near_end = ends[np.all(ends[..., 2] < 0, axis=1)]
    xy = view_coordinates(near_end, rotation, part.center).reshape(-1, 2)
    assert len(near_end) >= 8 and np.ptp(xy[:, 0]) == pytest.approx(0.040, abs=2e-4)
    assert (view.kinds == OUTLINE).sum() == 2


def test_a_cube_in_front_hides_the_edges_behind_it(tmp_path):
    """A 20 mm cube 100 mm in front of the 50 mm one (towards the camera) covers its centre."""
    back = trimesh.creation.box((2 * HALF,) * 3).subdivide()
    front = trimesh.creation.box((0.02,) * 3)
    front.apply_translation((0.0, 0.0, -0.1))
    path = tmp_path / "two.ply"
    trimesh.util.concatenate([back, front]).export(str(path))
    part, rotation, view = visible(path, (0.05, 0.08, 1))
    points = view.segments_3d[:, 0] + np.linspace(0, 1, 50)[:, None, None] * np.diff(view.segments_3d, axis=1)[:, 0]
    points = points.reshape(-1, 3)
    on_back = points[points[:, 2] > -0.05]
    behind_front = np.all(np.abs(view_coordinates(on_back, rotation, part.center)
                                 - view_coordinates(np.array([[0, 0, -0.1]]), rotation, part.center)) < 0.0095,
                          axis=1)
    assert len(on_back) > 0 and not behind_front.any()
    assert np.isclose(np.abs(points[points[:, 2] < -0.05]), [0.01, 0.01, 0.09], atol=1e-9).any(axis=1).all()


# ----------------------------------------------------------------------------- the file

@pytest.fixture(scope="module")
def cylinder_graph(cylinder_stl):
    return compile_aspect_graph(cylinder_stl, step_deg=30.0, workers=1, progress=False, units="mm")


def test_mesh_graph_is_the_checked_format_and_records_its_source(cylinder_graph, cylinder_stl, cube_ply, tmp_path):
    graph = cylinder_graph
    assert graph.params["source"] == "mesh" and graph.params["source_units"] == "mm"
    assert graph.params["units"] == "m" and graph.n_faces == 256
    assert np.diff(graph.seg_offsets).min() >= 3
    assert np.allclose(graph.model_center, 0.0)
    assert graph.model_diameter == pytest.approx(np.sqrt(0.04 ** 2 * 2 + 0.05 ** 2), rel=1e-3)
    loaded = AspectGraph.load(graph.save(tmp_path / "cylinder.brepose.npz"), step_path=cylinder_stl)
    for name, array in graph.arrays().items():
        assert np.array_equal(array, getattr(loaded, name)), name
    with pytest.raises(AspectGraphError, match="different STEP file"):
        AspectGraph.load(tmp_path / "cylinder.brepose.npz", step_path=cube_ply)


@pytest.mark.slow
def test_parallel_mesh_compile_gives_the_same_graph(cylinder_graph, cylinder_stl):
    parallel = compile_aspect_graph(cylinder_stl, step_deg=30.0, workers=2, progress=False, units="mm")
    for name, array in cylinder_graph.arrays().items():
        assert np.array_equal(array, getattr(parallel, name)), name


def test_cli_compiles_a_mesh_and_refuses_one_without_units(cylinder_stl, tmp_path, capsys):
    from brepose_ros.cli.compile import main

    out = tmp_path / "cylinder.brepose.npz"
    assert main([str(cylinder_stl), "--units", "mm", "-o", str(out), "--step-deg", "40", "--workers", "1", "-q"]) == 0
    assert AspectGraph.load(out).params["source_units"] == "mm"
    assert main([str(cylinder_stl), "-o", str(out), "-q"]) == 2
    assert "give its length unit with --units" in capsys.readouterr().err
    assert main([str(cylinder_stl), "--units", "mm", "--method", "exact", "-q"]) == 2
    assert "does not apply to meshes" in capsys.readouterr().err


def test_units_are_refused_for_a_step_file(sample_step):
    with pytest.raises(ValueError, match="units apply to mesh files only"):
        compile_aspect_graph(sample_step, step_deg=60.0, workers=1, progress=False, units="mm")


# ----------------------------------------------------------------------------- the estimator

@pytest.fixture(scope="module")
def bracket_mesh(builtin_step, tmp_path_factory):
    """The sharp bracket's tessellation written as a binary STL in mm: a mesh-only part."""
    mesh = tessellate(load_step(builtin_step("sharp_bracket")))
    path = tmp_path_factory.mktemp("meshes") / "sharp_bracket.stl"
    trimesh.Trimesh(mesh.vertices * 1000.0, mesh.triangles).export(str(path))
    return path, mesh


@pytest.mark.slow
def test_estimator_finds_a_rendered_mesh_part_from_its_mesh_graph(bracket_mesh):
    path, mesh = bracket_mesh
    graph = compile_aspect_graph(path, step_deg=10.0, workers=2, progress=False, units="mm")
    camera = Camera.from_fov(640, 480, 600.0)
    R = look_at_rotation(normalize(np.array([0.45, -0.6, 0.66])))  # a generic view
    t = np.array([0.004, -0.003, 0.32]) - R @ graph.model_center
    image = render(camera, [Placed(Mesh(mesh.vertices, mesh.triangles, mesh.normals), R, t)], background=40.0).image
    estimator = Estimator(graph)
    estimate = estimator.estimate(image, camera)
    estimator.close()
    assert estimate.found
    assert rotation_angle_deg(estimate.R, R) < 3.0
    assert np.linalg.norm(estimate.t - t) < 0.03 * graph.model_diameter


@pytest.mark.slow
def test_lmo_photo_edges_lie_on_the_compiled_mesh_lines(shared_data):
    """One real LM-O frame end to end: the ape's scanned mesh (mm) compiles, and at the
    true pose its lines fall on the photo's edges, far more than at a pose 10 px off; the
    mesh's vertex colours find the ape's place: its colour regions hold its lines and
    little of the rest of the photo."""
    folder = shared_data / "real" / "lmo_test_000002"
    graph = compile_aspect_graph(folder / "models" / "obj_000001.ply", step_deg=20.0, workers=2,
                                 progress=False, units="mm")
    truth = next(g for g in json.loads((folder / "scene_gt.json").read_text())["79"] if g["obj_id"] == 1)
    R, t = np.array(truth["cam_R_m2c"]).reshape(3, 3), np.array(truth["cam_t_m2c"]) / 1000.0
    camera = Camera.load(folder / "camera.json")
    image = cv2.imread(str(folder / "rgb" / "000079.png"))
    edges = detect_edges(image)
    evidence = EdgeEvidence(edges.edge_map, edges.gradient_x, edges.gradient_y)
    lines = graph.seg_3d[graph.visible_segments(R, t)]
    one_pose = np.array([0, len(lines)])
    at_truth = evidence.supports(camera.project_model(lines, R, t), one_pose, 2.0)[0]
    off = evidence.supports(camera.project_model(lines, R, t + [10.0 * t[2] / camera.fx, 0, 0]), one_pose, 2.0)[0]
    assert at_truth > 0.7 and at_truth > 1.5 * off  # measured: 0.80 and 0.43 (a cluttered desk)
    regions = colour_regions(image, graph.colour_histogram, EdgeParams().colour_region_threshold, 400)
    ends = np.round(camera.project_model(lines, R, t).reshape(-1, 2)).astype(int)
    assert regions[ends[:, 1], ends[:, 0]].mean() > 0.95 and regions.mean() < 0.25

"""View sphere, hidden-line removal and the aspect graph file, on parts with known answers."""
from __future__ import annotations

import dataclasses
import json
import struct
import zipfile

import numpy as np
import pytest
from scipy.spatial import cKDTree

from brepose_ros.aspect_graph import AspectGraph, AspectGraphError
from brepose_ros.offline.compiler import compile_aspect_graph
from brepose_ros.offline.cad import load_step
from brepose_ros.geometry import look_at_rotation, normalize
from brepose_ros.offline.hidden_lines import METHODS, OUTLINE, SHARP, HiddenLineRemover, view_coordinates
from brepose_ros.online.kernels import nearest_views_kernel
from brepose_ros.viewsphere import direction_cells, fibonacci_directions, lonlat_directions, nearest_views, view_ups


# ----------------------------------------------------------------------------- view sphere

@pytest.mark.parametrize("step_deg", [5.0, 30.0])
def test_golden_spiral_neighbours_are_about_one_step_apart(step_deg):
    directions = fibonacci_directions(step_deg)
    assert np.allclose(np.linalg.norm(directions, axis=1), 1.0)
    distance, _ = cKDTree(directions).query(directions, k=2)
    spacing = np.degrees(2.0 * np.arcsin(distance[:, 1] / 2.0))
    assert np.median(spacing) == pytest.approx(step_deg, rel=0.05)
    assert spacing.min() > 0.8 * step_deg  # no crowding anywhere, poles included


def test_lonlat_grid_has_the_papers_layout():
    directions = lonlat_directions(24)
    assert len(directions) == 24 * 23 + 2
    assert np.allclose(directions[[0, -1]], [[0, 0, -1], [0, 0, 1]])
    latitudes = np.degrees(np.arcsin(directions[1:-1, 2]))
    assert np.allclose(np.unique(latitudes.round(6)), -90 + 7.5 * np.arange(1, 24))


def test_nearest_views_are_sorted_by_angle():
    directions = fibonacci_directions(10.0)
    query = normalize(directions[7] + 0.01)
    nearest = nearest_views(directions, query, k=3)
    assert nearest[0] == 7
    angles = np.arccos(np.clip(directions[nearest] @ query, -1, 1))
    assert np.all(np.diff(angles) >= 0)
    assert nearest_views(directions, directions[:4], k=3).shape == (4, 3)


@pytest.mark.parametrize("directions", [fibonacci_directions(3.0), fibonacci_directions(40.0), lonlat_directions(7),
                                        np.array([[0.0, 0.0, -1.0]])], ids=["spiral-3", "spiral-40", "lonlat", "one"])
def test_the_cells_nearest_view_is_every_views(directions):
    """The cell look-up gives the view of the scan over all views, the first of equal products
    too: at random poses, at poses seen exactly along a view and along a cube edge, at a
    direction of rounding noise about zero, and at a NaN one (the scan's view 0)."""
    rng = np.random.default_rng(5)
    n = 20000
    center = np.array([0.01, -0.02, 0.005])
    q, _ = np.linalg.qr(rng.normal(size=(n, 3, 3)))
    R = np.ascontiguousarray(q)
    seen = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 1e3], size=(n, 1))  # R^T t + c, any scale
    seen[:200] = directions[rng.integers(0, len(directions), 200)] * 0.4
    seen[200:210] = normalize(np.array([1.0, 1.0, 0.0])) * 0.3
    seen[210:212], seen[212] = 0.0, np.nan
    t = np.einsum("bij,bj->bi", R, seen - center)
    cells = direction_cells(directions)
    assert len(cells[0]) > 1 and np.all(np.diff(cells[0]) > 0)
    scanned, looked_up = np.empty(n, np.int64), np.empty(n, np.int64)
    none = np.zeros(0, np.int64)
    nearest_views_kernel(R, t, directions, center, none, none, scanned)
    nearest_views_kernel(R, t, directions, center, *cells, looked_up)
    assert np.array_equal(scanned, looked_up)
    assert scanned[212] == 0


def test_directions_that_are_not_unit_get_no_cells():
    assert all(len(a) == 0 for a in direction_cells(fibonacci_directions(30.0) * 1.01))


# ----------------------------------------------------------------------------- hidden lines

def visible(step, direction, method, **options):
    part = load_step(step)
    rotation = look_at_rotation(normalize(np.asarray(direction, dtype=float)))
    return part, rotation, HiddenLineRemover(part, method=method, **options).segments(rotation)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("direction, count", [((0, 0, -1), 4), ((1, 1, 1), 9), ((0.2, 0.3, -1), 9)],
                         ids=["face-on", "body-diagonal", "oblique"])
def test_box_shows_its_visible_edges_once(builtin_step, method, direction, count):
    part, rotation, view = visible(builtin_step("box"), direction, method)
    assert len(view.kinds) == count and np.all(view.kinds == SHARP)
    # Every 3D end point is a corner of the box, and projects to its 2D end point.
    corners = np.array([[x, y, z] for x in (-0.03, 0.03) for y in (-0.02, 0.02) for z in (-0.0125, 0.0125)])
    distance, _ = cKDTree(corners).query(view.segments_3d.reshape(-1, 3))
    assert distance.max() < 1e-9
    xy = view_coordinates(view.segments_3d, rotation, part.center)
    expected = (view.segments_3d - part.center) @ rotation[:2].T
    assert np.allclose(xy, expected)


@pytest.mark.parametrize("method", METHODS)
def test_cylinder_side_on_shows_two_outlines_and_its_two_end_lines(builtin_step, method):
    part, rotation, view = visible(builtin_step("cylinder"), (1, 0, 0), method)  # r 20, h 50 mm
    assert sorted(view.kinds.tolist()) == [SHARP, SHARP, OUTLINE, OUTLINE]
    xy = view_coordinates(view.segments_3d, rotation, part.center)
    outline = xy[view.kinds == OUTLINE]
    assert np.allclose(np.sort(np.abs(outline[..., 0]).ravel()), 0.020, atol=2e-4)  # x = +-r
    ends = xy[view.kinds == SHARP]
    assert np.allclose(np.abs(ends[..., 1]), 0.025, atol=1e-6)  # the end circles seen edge-on
    assert np.allclose(np.abs(ends[:, 1, 0] - ends[:, 0, 0]), 0.040, atol=2e-4)


@pytest.mark.parametrize("method", METHODS)
def test_cylinder_seen_obliquely_shows_an_ellipse_within_the_chord_tolerance(builtin_step, method):
    part, rotation, view = visible(builtin_step("cylinder"), (1, 0, 0.6), method)
    ends = view.segments_3d[view.kinds == SHARP]
    radius = np.linalg.norm(ends[..., :2], axis=2)  # 3D end points lie on the end circles
    assert np.allclose(radius, 0.020, atol=1e-3 * part.diameter)
    near_end = ends[np.all(ends[..., 2] < 0, axis=1)]  # seen from below: the whole bottom ellipse
    xy = view_coordinates(near_end, rotation, part.center).reshape(-1, 2)
    assert len(near_end) >= 8 and np.ptp(xy[:, 0]) == pytest.approx(0.040, abs=1e-3)


@pytest.fixture(scope="module")
def blind_hole_step(tmp_path_factory):
    """A 60 x 40 x 20 mm block with a 16 mm hole drilled 10 mm deep from its bottom face."""
    import cadquery as cq

    from brepose_ros.synthetic import shapes

    block = cq.Workplane("XY").box(60, 40, 20).faces("<Z").workplane().hole(16, 10)
    return shapes.export_step(block, tmp_path_factory.mktemp("blind") / "blind_hole.step")


@pytest.mark.cad
@pytest.mark.parametrize("method", METHODS)
def test_hole_behind_a_face_does_not_appear(blind_hole_step, method):
    _, _, top = visible(blind_hole_step, (0.2, 0.3, -1), method)  # looking down at the top
    assert len(top.kinds) == 9
    on_box_surface = np.isclose(np.abs(top.segments_3d), [0.03, 0.02, 0.01], atol=1e-9).any(axis=2)
    assert on_box_surface.all()
    hole_radius = np.linalg.norm(top.segments_3d[..., :2], axis=2)
    assert (hole_radius > 0.0081).all()
    _, _, bottom = visible(blind_hole_step, (0.2, 0.3, 1), method)  # looking up: the hole shows
    assert np.isclose(np.linalg.norm(bottom.segments_3d[..., :2], axis=2), 0.008, atol=2e-4).any()


def occt_2d_edges(shape, rotation):
    """OCCT's own 2D hidden-line result, densely sampled, in our view coordinates."""
    from OCP.BRepAdaptor import BRepAdaptor_Curve
    from OCP.TopAbs import TopAbs_EDGE
    from OCP.TopExp import TopExp_Explorer
    from OCP.TopoDS import TopoDS

    from brepose_ros.offline.hidden_lines import exact_hidden_lines

    result = exact_hidden_lines(shape, rotation)
    points = []
    for compound in (result.VCompound(), result.OutLineVCompound()):
        explorer = TopExp_Explorer(compound, TopAbs_EDGE)
        while explorer.More():
            curve = BRepAdaptor_Curve(TopoDS.Edge_s(explorer.Current()))
            for u in np.linspace(curve.FirstParameter(), curve.LastParameter(), 2000):
                x, y, _ = curve.Value(u).Coord()
                points.append((x, -y))  # the projector's 2D y axis is -y
            explorer.Next()
    return np.array(points)


def test_exact_3d_end_points_project_onto_occts_2d_result(builtin_step):
    part, rotation, view = visible(builtin_step("rounded_bracket"), (0.4, -0.7, 0.6), "exact")
    reference = cKDTree(occt_2d_edges(part.shape, rotation) - rotation[:2] @ part.center)
    ends = view_coordinates(view.segments_3d, rotation, part.center).reshape(-1, 2)
    distance, _ = reference.query(ends)
    assert distance.max() < 3e-4 * part.diameter  # half the reference's sample spacing
    middles = view_coordinates(view.segments_3d.mean(axis=1), rotation, part.center)
    assert reference.query(middles)[0].max() <= 0.005 * part.diameter  # the chord tolerance


def test_poly_mode_finds_the_same_lines_as_exact(builtin_step):
    step, direction = builtin_step("rounded_bracket"), (0.4, -0.7, 0.6)
    part, rotation, exact = visible(step, direction, "exact", min_length=0.0)
    _, _, poly = visible(step, direction, "poly", min_length=0.0)

    def samples(view):
        t = np.linspace(0.0, 1.0, 20)[:, None, None]
        xy = view_coordinates(view.segments_3d, rotation, part.center)
        return (xy[:, 0] * (1 - t) + xy[:, 1] * t).reshape(-1, 2)

    for found, reference in ((samples(poly), samples(exact)), (samples(exact), samples(poly))):
        distance, _ = cKDTree(reference).query(found)
        assert np.mean(distance < 0.01 * part.diameter) > 0.97


# ----------------------------------------------------------------------------- aspect graph

@pytest.fixture(scope="module")
def graph(sample_step):
    return compile_aspect_graph(sample_step, step_deg=30.0, workers=1, progress=False)


def test_graph_layout_follows_the_view_coordinate_convention(graph):
    assert graph.n_views == len(fibonacci_directions(30.0)) == len(graph.xy_scale)
    assert graph.seg_offsets[0] == 0 and graph.seg_offsets[-1] == graph.n_segments
    assert graph.seg_xy.shape == (graph.n_segments, 2, 2) and graph.seg_3d.dtype == np.float64
    assert graph.params["units"] == "m" and graph.params["method"] in METHODS
    for i in range(graph.n_views):
        rotation = look_at_rotation(graph.view_directions[i], view_ups(graph.view_directions[i:i + 1])[0])
        assert np.allclose(graph.view_rotations[i], rotation)
        xy = (graph.seg_3d[graph.view_slice(i)] - graph.model_center) @ rotation[:2].T
        # float32 storage relative to the view's own size: 7 digits of the part's diameter
        assert np.abs(graph.view_xy(i) - xy).max() < 1e-6 * graph.model_diameter
        assert np.abs(graph.seg_xy[graph.view_slice(i)]).max() < 10.0  # relative to the view's own unit


@pytest.mark.slow
def test_parallel_compile_gives_the_same_graph(sample_step, graph):
    parallel = compile_aspect_graph(sample_step, step_deg=30.0, workers=2, progress=False)
    for name, array in graph.arrays().items():
        assert np.array_equal(array, getattr(parallel, name)), name


def test_save_load_round_trip_is_identical(graph, sample_step, tmp_path):
    path = graph.save(tmp_path / "sample.brepose.npz")
    assert path.stat().st_mode & 0o777 == 0o644
    loaded = AspectGraph.load(path, step_path=sample_step)
    for name, array in graph.arrays().items():
        assert array.dtype == getattr(loaded, name).dtype and np.array_equal(array, getattr(loaded, name)), name
    assert (loaded.params, loaded.step_sha256, loaded.n_faces, loaded.model_diameter) == \
        (graph.params, graph.step_sha256, graph.n_faces, graph.model_diameter)
    with np.load(path, allow_pickle=False) as npz:  # plain data: no pickled objects inside
        assert all(npz[name].dtype != object for name in npz.files)


def test_the_graph_holds_the_parts_surface_and_reads_without_it(graph, tmp_path):
    """The tessellated surface within the part's box with unit normals, kept through a save;
    a graph written before graphs held it reads with no surface."""
    surface = graph.surface
    assert len(surface.triangles) > 12 and surface.triangles.max() < len(surface.vertices)
    assert np.allclose(np.linalg.norm(surface.normals, axis=1), 1.0, atol=1e-5)
    assert np.linalg.norm(np.ptp(surface.vertices, axis=0)) == pytest.approx(graph.model_diameter, rel=0.01)
    loaded = AspectGraph.load(graph.save(tmp_path / "sample.brepose.npz"))
    assert np.array_equal(loaded.surface.vertices, surface.vertices)
    older = dataclasses.replace(graph, surface_vertices=None, surface_normals=None, surface_triangles=None)
    assert AspectGraph.load(older.save(tmp_path / "older.brepose.npz")).surface is None


def missing(path, tmp_path):
    return tmp_path / "absent.brepose.npz"


def shell_script(path, tmp_path):
    path.write_text("#!/bin/sh\necho not data\n")
    return path


def cut_in_half(path, tmp_path):
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return path


def flip_byte_in_array(path, tmp_path):
    """Flip one bit inside seg_3d's stored (deflated) bytes."""
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("seg_3d.npy")
    data = bytearray(path.read_bytes())
    name_length, extra_length = struct.unpack("<HH", data[info.header_offset + 26: info.header_offset + 30])
    data[info.header_offset + 30 + name_length + extra_length + info.compress_size // 2] ^= 0x01
    path.write_bytes(bytes(data))
    return path


def rewritten(**changes):
    """A damage: rewrite the file (a valid zip again) with entries or metadata fields changed;
    a change returning None removes the entry or field."""
    def damage(path, tmp_path):
        with np.load(path, allow_pickle=False) as npz:
            entries = {name: npz[name] for name in npz.files}
        metadata = json.loads(str(entries["metadata"]))
        for key, change in changes.items():
            if key in entries:
                entries[key] = change(entries[key])
            else:
                metadata[key] = change(metadata[key])
        entries = {name: a for name, a in entries.items() if a is not None}
        entries["metadata"] = np.array(json.dumps({k: v for k, v in metadata.items() if v is not None}))
        with open(path, "wb") as stream:
            np.savez(stream, **entries)
        return path
    return damage


@pytest.mark.parametrize("damage, message", [
    (missing, "does not exist"),
    (shell_script, "not an aspect graph file"),
    (cut_in_half, "is truncated"),
    (flip_byte_in_array, "modified after it was written"),
    (rewritten(seg_3d=lambda a: a + 1e-6), "content digest mismatch"),
    (rewritten(params=lambda d: {**d, "chord_tolerance": 0.5}), "content digest mismatch"),
    (rewritten(format_version=lambda v: v + 1), "newer than this brepose_ros"),
    (rewritten(format_version=lambda v: 1, seg_xy=lambda a: None), "format version 1 is older .* recompile it"),
    (rewritten(seg_xy=lambda a: None), "lacks the array"),
    (rewritten(step_sha256=lambda a: None), "metadata lacks step_sha256"),
    (rewritten(seg_kind=lambda a: a.astype(np.int64)), "array seg_kind has dtype int64"),
    (rewritten(xy_scale=lambda a: a[:-1]), "array xy_scale has dtype .* shape"),
    (rewritten(surface_triangles=lambda a: a + 10 ** 6), "surface_triangles .* indexes a vertex outside"),
    (rewritten(surface_normals=lambda a: a * 2), "surface_normals holds a vector that is not a unit normal"),
    (rewritten(surface_normals=lambda a: None), "holds surface_vertices, surface_triangles but not all"),
], ids=["missing", "not-npz", "truncated", "flipped-byte", "array-edited", "metadata-edited", "newer-version",
        "older-version", "missing-array", "missing-metadata", "wrong-dtype", "wrong-shape", "surface-index",
        "surface-normals", "surface-partial"])
def test_damaged_files_are_refused_naming_the_cause(graph, tmp_path, damage, message):
    path = damage(graph.save(tmp_path / "sample.brepose.npz"), tmp_path)
    with pytest.raises(AspectGraphError, match=message):
        AspectGraph.load(path)


def test_graph_of_another_step_file_is_refused(graph, builtin_step, tmp_path):
    path = graph.save(tmp_path / "sample.brepose.npz")
    with pytest.raises(AspectGraphError, match="different STEP file"):
        AspectGraph.load(path, step_path=builtin_step("box"))


def test_cli_compiles_and_reports_errors_with_status_2(sample_step, tmp_path, capsys):
    from brepose_ros.cli.compile import main

    out = tmp_path / "sample.brepose.npz"
    assert main([str(sample_step), "-o", str(out), "--lonlat", "4", "--workers", "1", "-q"]) == 0
    assert "14 views" in capsys.readouterr().out and AspectGraph.load(out).params["lonlat"] == 4
    assert main([str(tmp_path / "missing.step"), "-q"]) == 2
    assert "does not exist" in capsys.readouterr().err


# ----------------------------------------------------------------------------- real parts

@pytest.mark.slow
def test_every_real_part_compiles(shared_data, tmp_path):
    steps = sorted((shared_data / "step").glob("*.st*p"))
    assert len(steps) == 9
    for step in steps:
        graph = compile_aspect_graph(step, step_deg=36.0, workers=1, progress=False)
        counts = np.diff(graph.seg_offsets)
        assert graph.n_views == 29 and counts.min() >= 3, step.name
        lo, hi = graph.seg_3d.reshape(-1, 3).min(axis=0), graph.seg_3d.reshape(-1, 3).max(axis=0)
        half = graph.model_diameter / 2
        assert np.all(np.abs(np.stack([lo, hi]) - graph.model_center) <= half * 1.001), step.name
        AspectGraph.load(graph.save(tmp_path / f"{step.stem}.brepose.npz"), step_path=step)

"""The mesh loader: units to metres once, the model frame kept, every unusable file refused
with a message naming the cause."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from brepose_ros.offline.mesh import MeshError, edge_topology, load_mesh

trimesh = pytest.importorskip("trimesh")  # the [compile] extra
pytestmark = pytest.mark.cad


def cube(size=0.05, offset=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    box = trimesh.creation.box((size, size, size))
    box.apply_translation(offset)
    return box


def write(mesh: trimesh.Trimesh, path, **kwargs):
    mesh.export(str(path), **kwargs)
    return path


def outward(part) -> bool:
    corners = part.vertices[part.triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    return bool(np.all(np.einsum("ij,ij->i", normals, corners.mean(axis=1) - part.center) > 0))


@pytest.mark.parametrize("suffix", ["ply", "stl", "obj"])
def test_mesh_is_read_in_its_units_and_keeps_its_frame(tmp_path, suffix):
    part = load_mesh(write(cube(50.0, offset=(100.0, 0.0, -20.0)), tmp_path / f"cube.{suffix}"), "mm")
    assert part.n_faces == 12 and len(part.vertices) == 8  # an STL's 36 corners merged into 8
    assert np.allclose(part.center, [0.1, 0.0, -0.02])  # mm -> m, not re-centred
    assert part.diameter == pytest.approx(np.sqrt(3) * 0.05)
    assert part.units == "mm" and outward(part)


def test_inches_are_converted(tmp_path):
    part = load_mesh(write(cube(2.0), tmp_path / "cube.ply"), "in")
    assert np.ptp(part.vertices, axis=0) == pytest.approx([0.0508] * 3)


def test_flipped_and_inside_out_triangles_are_turned_outward(tmp_path):
    mesh = cube(1.0).subdivide()
    faces = mesh.faces.copy()
    faces[::3] = faces[::3, ::-1]  # a third of the triangles flipped
    part = load_mesh(write(trimesh.Trimesh(mesh.vertices, faces, process=False), tmp_path / "mixed.ply"), "m")
    assert outward(part)
    inverted = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    assert outward(load_mesh(write(inverted, tmp_path / "inverted.ply"), "m"))


def test_edge_topology_pairs_the_two_triangles_of_each_edge():
    topology = edge_topology(cube().faces)
    assert len(topology.vertices) == 18 and topology.manifold.all()  # 12 cube edges + 6 diagonals
    for (a, b), (f, g) in zip(topology.vertices, topology.faces):
        assert {a, b} <= set(cube().faces[f]) and {a, b} <= set(cube().faces[g]) and f != g


def binary_ply_cut(tmp_path):
    data = write(cube(), tmp_path / "full.ply", encoding="binary").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) - 40])
    return tmp_path / "cut.ply"


def binary_stl_cut(tmp_path):
    data = write(cube(), tmp_path / "full.stl").read_bytes()
    (tmp_path / "cut.stl").write_bytes(data[: len(data) - 25])
    return tmp_path / "cut.stl"


def ascii_stl_cut(tmp_path):
    text = trimesh.exchange.stl.export_stl_ascii(cube())
    (tmp_path / "cut.stl").write_text(text[: len(text) // 2])
    return tmp_path / "cut.stl"


def nan_vertex(tmp_path):
    text = write(cube(), tmp_path / "cube.ply", encoding="ascii").read_text().splitlines()
    first = text.index("end_header") + 1
    text[first] = "nan 0 0"
    (tmp_path / "nan.ply").write_text("\n".join(text) + "\n")
    return tmp_path / "nan.ply"


def triangle_soup(tmp_path):
    """Triangles that share no edge: an export that lost its connectivity."""
    triangles = np.arange(30).reshape(10, 3)
    vertices = np.random.default_rng(0).random((30, 3))
    return write(trimesh.Trimesh(vertices, triangles, process=False), tmp_path / "soup.ply")


def text_file(tmp_path):
    (tmp_path / "notes.obj").write_bytes(b"\x00\x01 these are not the droids\n")
    return tmp_path / "notes.obj"


def no_triangles(tmp_path):
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    return tmp_path / "points.obj"


def flat_sliver(tmp_path):
    (tmp_path / "line.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    return tmp_path / "line.obj"


def empty(tmp_path):
    (tmp_path / "empty.stl").touch()
    return tmp_path / "empty.stl"


@pytest.mark.parametrize("make, message", [
    (lambda tmp_path: tmp_path / "missing.ply", "does not exist"),
    (empty, "is empty"),
    (lambda tmp_path: write(cube(), tmp_path / "cube.glb"), "not a mesh file this reads"),
    (text_file, "not an OBJ file"),
    (binary_ply_cut, "not a readable PLY"),
    (binary_stl_cut, "truncated or not an STL"),
    (ascii_stl_cut, "is truncated"),
    (nan_vertex, "1 vertices with NaN"),
    (no_triangles, "holds no triangles"),
    (flat_sliver, "no triangle of non-zero area"),
    (triangle_soup, "is not a surface"),
], ids=["missing", "empty", "unknown-suffix", "binary-obj", "truncated-ply", "truncated-binary-stl",
        "truncated-ascii-stl", "nan", "no-triangles", "degenerate", "soup"])
def test_unusable_mesh_files_are_refused(tmp_path, make, message):
    with pytest.raises(MeshError, match=message):
        load_mesh(make(tmp_path), "mm")


@pytest.mark.parametrize("units", [None, "furlong"])
def test_a_mesh_needs_its_unit(tmp_path, units):
    with pytest.raises(MeshError, match="needs its length unit"):
        load_mesh(write(cube(), tmp_path / "cube.ply"), units)


def test_huge_meshes_are_refused_before_and_after_parsing(tmp_path):
    path = write(cube().subdivide(), tmp_path / "cube.ply")
    with pytest.raises(MeshError, match="48 triangles, over the limit of 20"):
        load_mesh(path, "m", max_faces=20)  # the PLY header's count, before parsing
    with pytest.raises(MeshError, match="over the limit of 20"):
        load_mesh(write(cube().subdivide(), tmp_path / "cube.obj"), "m", max_faces=20)
    with pytest.raises(MeshError, match="MB, over the limit"):
        load_mesh(path, "m", max_bytes=100)


def test_a_binary_stl_header_claiming_more_than_the_limit_is_refused(tmp_path):
    path = tmp_path / "claims.stl"
    path.write_bytes(b"\0" * 80 + struct.pack("<I", 10_000_000) + b"\0" * 50)
    with pytest.raises(MeshError, match="truncated or not an STL"):
        load_mesh(path, "mm")


def test_a_meshs_vertex_colours_become_its_colour_histogram_and_none_without(tmp_path):
    from brepose_ros.chromaticity import BINS

    coloured = cube(50.0)
    coloured.visual.vertex_colors = np.tile([150, 60, 50, 255], (len(coloured.vertices), 1))  # RGBA brown
    histogram = load_mesh(write(coloured, tmp_path / "brown.ply"), "mm").colour_histogram
    r, g = int(151 / 263 * BINS), int(61 / 263 * BINS)  # (R + 1, G + 1) / (R + G + B + 3)
    assert histogram.sum() == pytest.approx(1.0) and np.unravel_index(histogram.argmax(), histogram.shape) == (r, g)
    assert load_mesh(write(cube(50.0), tmp_path / "plain.ply"), "mm").colour_histogram is None
    assert load_mesh(write(cube(50.0), tmp_path / "plain.stl"), "mm").colour_histogram is None

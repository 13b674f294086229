"""Meshes of the things that occlude or clutter a scene: bars, pipes, blobs, polygon plates
and glued-together blocks that look like other machined parts.

Each ``unit_prop`` lies along its x axis with a longest extent of 1 and is centred at the
origin; ``stretched`` sizes it. Flat faces carry their own normals (sharp edges in the image),
blobs smooth vertex normals (soft outlines), as the renderer expects (``render.shade``).
"""
from __future__ import annotations

import numpy as np

from ..geometry import normalize
from ..offline.cad import Mesh, vertex_normals

#: Elongated props (sized by a length and a width) and compact ones (sized by their width).
ELONGATED = ("bar", "pipe")
COMPACT = ("blob", "polygon", "blocks")
#: "part" is a whole other part's mesh, available when the scene is given some.
KINDS = ELONGATED + COMPACT


def box_mesh(dx: float, dy: float, dz: float) -> Mesh:
    """A box centred at the origin with flat faces (four vertices each)."""
    half = np.array([dx, dy, dz]) / 2.0
    vertices, normals, triangles = [], [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            u, v = np.eye(3)[(axis + 1) % 3], np.eye(3)[(axis + 2) % 3]
            if sign < 0:
                u, v = v, u  # keep u x v = outward normal, so triangles stay counter-clockwise
            normal = sign * np.eye(3)[axis]
            corners = [normal + a * u + b * v for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
            base = len(vertices)
            vertices += [c * half for c in corners]
            normals += [normal] * 4
            triangles += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return Mesh(np.array(vertices), np.array(triangles, dtype=np.int32), np.array(normals))


def cylinder_mesh(radius: float, length: float, segments: int = 32) -> Mesh:
    """A closed cylinder along z centred at the origin: smooth side, flat caps."""
    angles = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles), np.zeros(segments)], axis=1)
    return prism_mesh(radius * ring[:, :2], length, smooth_sides=True)


def prism_mesh(outline: np.ndarray, thickness: float, smooth_sides: bool = False) -> Mesh:
    """A plate along z (centred) whose cross-section is a polygon, counter-clockwise and
    star-shaped about the origin (the caps are fans from it). Sides are flat faces, or one
    smooth surface (``smooth_sides``: normals radial, as for a cylinder)."""
    n = len(outline)
    k, k1 = np.arange(n), (np.arange(n) + 1) % n
    lo = np.column_stack([outline, np.full(n, -thickness / 2)])
    hi = np.column_stack([outline, np.full(n, thickness / 2)])
    up = np.array([0.0, 0.0, 1.0])
    caps = [lo, hi, [[0.0, 0.0, -thickness / 2], [0.0, 0.0, thickness / 2]]]
    cap_normals = [np.tile(-up, (n, 1)), np.tile(up, (n, 1)), [-up, up]]
    c = 2 * n  # index of the bottom centre within the caps block
    cap_triangles = [np.stack([np.full(n, c), k1, k], axis=1),
                     np.stack([np.full(n, c + 1), n + k, n + k1], axis=1)]
    if smooth_sides:
        side_vertices = [lo, hi]
        radial = normalize(np.column_stack([outline, np.zeros(n)]))
        side_normals = [radial, radial]
        side_triangles = [np.stack([k, k1, n + k1], axis=1), np.stack([k, n + k1, n + k], axis=1)]
    else:  # four vertices per side face, its own outward normal
        side_vertices = [np.stack([lo[k], lo[k1], hi[k1], hi[k]], axis=1).reshape(-1, 3)]
        edge = outline[k1] - outline[k]
        outward = normalize(np.column_stack([edge[:, 1], -edge[:, 0], np.zeros(n)]))
        side_normals = [np.repeat(outward, 4, axis=0)]
        q = 4 * k
        side_triangles = [np.stack([q, q + 1, q + 2], axis=1), np.stack([q, q + 2, q + 3], axis=1)]
    sides = len(np.concatenate(side_vertices))
    vertices = np.concatenate(side_vertices + [np.asarray(v, float) for v in caps])
    normals = np.concatenate(side_normals + [np.asarray(v, float) for v in cap_normals])
    triangles = np.concatenate(side_triangles + [t + sides for t in cap_triangles])
    return Mesh(vertices, triangles.astype(np.int32), normals)


def blob_mesh(rng: np.random.Generator, rows: int = 14, columns: int = 24) -> Mesh:
    """A smooth lumpy closed surface (a stone, a rag, a cable bundle's end): a sphere whose
    radius varies with a few random low-frequency waves, squashed along y and z."""
    theta = np.linspace(0.0, np.pi, rows + 1)[:, None]  # from +z to -z
    phi = np.linspace(0.0, 2.0 * np.pi, columns, endpoint=False)[None, :]
    radius = np.ones((rows + 1, columns))
    for _ in range(3):
        a, b = rng.integers(1, 4, size=2)
        phase = rng.uniform(0.0, 2.0 * np.pi, 2)
        radius += rng.uniform(0.05, 0.2) * np.sin(a * theta + phase[0]) * np.cos(b * phi + phase[1])
    radius[0], radius[-1] = radius[0].mean(), radius[-1].mean()  # one radius at each pole
    points = radius[..., None] * np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                                           np.cos(theta) * np.ones_like(phi)], axis=-1)
    points = points * np.array([1.0, rng.uniform(0.45, 0.9), rng.uniform(0.45, 0.9)])
    vertices = points.reshape(-1, 3)
    i, j = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
    a, b = i * columns + j, i * columns + (j + 1) % columns
    c, d = a + columns, b + columns
    triangles = np.concatenate([np.stack([a, c, d], -1).reshape(-1, 3),
                                np.stack([a, d, b], -1).reshape(-1, 3)]).astype(np.int32)
    return _centred_unit(Mesh(vertices, triangles, vertex_normals(vertices, triangles)))


def polygon_plate(rng: np.random.Generator) -> Mesh:
    """A flat plate with a random 3- to 8-sided outline (a sheet, a guard, a tray). Corners are
    jittered around even angles, so no gap reaches half a turn and the outline stays
    star-shaped about the origin."""
    sides = int(rng.integers(3, 9))
    step = 2.0 * np.pi / sides
    angles = np.arange(sides) * step + rng.uniform(-0.2, 0.2, sides) * step
    radius = rng.uniform(0.55, 1.0, sides)
    outline = np.column_stack([radius * np.cos(angles), radius * np.sin(angles)])
    return _centred_unit(prism_mesh(outline, rng.uniform(0.05, 0.2)))


def blocks(rng: np.random.Generator) -> Mesh:
    """Two to four boxes and cylinders glued together: something that looks like another
    machined part, with straight edges and round ones (the z-buffer resolves the overlaps)."""
    pieces = []
    for _ in range(int(rng.integers(2, 5))):
        size = rng.uniform(0.15, 0.6, 3)
        if rng.random() < 0.35:
            piece = cylinder_mesh(size[0] / 2, size[2], segments=20)
        else:
            piece = box_mesh(*size)
        pieces.append(transformed(piece, _axis_turn(rng), rng.uniform(-0.25, 0.25, 3)))
    return _centred_unit(merged(pieces))


def unit_prop(kind: str, rng: np.random.Generator, parts: tuple[Mesh, ...] = ()) -> Mesh:
    """A prop of ``kind`` (``KINDS`` or "part", one of ``parts`` at random), longest side 1."""
    if kind == "bar":
        return box_mesh(1.0, 1.0, 1.0)
    if kind == "pipe":
        pipe = cylinder_mesh(0.5, 1.0)
        return transformed(pipe, np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]), np.zeros(3))
    if kind == "blob":
        return blob_mesh(rng)
    if kind == "polygon":
        return polygon_plate(rng)
    if kind == "blocks":
        return blocks(rng)
    if kind == "part" and parts:
        return _centred_unit(parts[int(rng.integers(len(parts)))])
    raise ValueError(f"unknown prop kind {kind!r}")


def stretched(mesh: Mesh, scale) -> Mesh:
    """The mesh scaled per axis; normals follow the inverse transpose."""
    scale = np.broadcast_to(np.asarray(scale, dtype=float), (3,))
    return Mesh(mesh.vertices * scale, mesh.triangles, normalize(mesh.normals / scale))


def transformed(mesh: Mesh, R: np.ndarray, t: np.ndarray) -> Mesh:
    return Mesh(mesh.vertices @ R.T + t, mesh.triangles, mesh.normals @ R.T)


def merged(meshes: list[Mesh]) -> Mesh:
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(np.concatenate([m.vertices for m in meshes]),
                np.concatenate([m.triangles + o for m, o in zip(meshes, offsets)]).astype(np.int32),
                np.concatenate([m.normals for m in meshes]))


def _axis_turn(rng: np.random.Generator) -> np.ndarray:
    """One of the 24 rotations that map axes onto axes (machined pieces meet square)."""
    R = np.eye(3)[rng.permutation(3)] * rng.choice([-1.0, 1.0], 3)[:, None]
    return R * np.sign(np.linalg.det(R))


def _centred_unit(mesh: Mesh) -> Mesh:
    """Centred on its bounding box, longest side 1."""
    low, high = mesh.vertices.min(axis=0), mesh.vertices.max(axis=0)
    return Mesh((mesh.vertices - (low + high) / 2) / (high - low).max(), mesh.triangles, mesh.normals)
